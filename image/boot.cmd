# exolink A/B boot selection: U-Boot's distro boot finds boot.scr (this file, wrapped by mkimage)
# on the card's FAT partition and runs it, on the BeagleBone (am335x_boneblack, mmc) and under
# qemu (-M virt with Debian's qemu_arm U-Boot, virtio): the same script on both.
#
# RAUC's U-Boot conventions: BOOT_ORDER ("A B": A first) and BOOT_<slot>_LEFT (attempts left).
# Each boot takes one attempt from the first slot in BOOT_ORDER that has one and boots it; the
# running system resets the count once it is up (`rauc status mark-good`, exolink-mark-good).
# A slot whose attempts ran out is skipped: the next boot falls back to the other one.
#
# They live in exolink-boot.env on the FAT (text, `env import -t` / `env export -t` + fatwrite),
# not in U-Boot's own environment: the BeagleBone's U-Boot keeps its environment at a raw offset
# and qemu_arm's in a flash the virt machine does not have, while the FAT file is read and written
# the same way by both, by RAUC's custom backend on Linux (rauc-boot-backend), and is visible on a
# laptop. The BeagleBone's U-Boot has no setexpr: the count goes down by a table (0..3).
#
# Partition 1: FAT, 2: root slot A, 3: root slot B (image/image.conf). The kernel, initrd and dtb
# are read from the chosen slot's /boot/exolink/, so an update replaces them with its root.

setenv exo_state exolink-boot.env
setenv BOOT_ORDER "A B"
setenv BOOT_A_LEFT 3
setenv BOOT_B_LEFT 3
if load ${devtype} ${devnum}:1 ${kernel_addr_r} ${exo_state}; then
  env import -t ${kernel_addr_r} ${filesize}
fi

setenv exo_slot
for s in ${BOOT_ORDER}; do
  if test "x${exo_slot}" = "x"; then
    if test "x${s}" = "xA"; then
      if test ${BOOT_A_LEFT} -gt 0; then
        setenv exo_slot A
        setenv exo_part 2
        if test ${BOOT_A_LEFT} -ge 3; then setenv BOOT_A_LEFT 2;
        elif test ${BOOT_A_LEFT} -eq 2; then setenv BOOT_A_LEFT 1;
        else setenv BOOT_A_LEFT 0; fi
      fi
    fi
    if test "x${s}" = "xB"; then
      if test ${BOOT_B_LEFT} -gt 0; then
        setenv exo_slot B
        setenv exo_part 3
        if test ${BOOT_B_LEFT} -ge 3; then setenv BOOT_B_LEFT 2;
        elif test ${BOOT_B_LEFT} -eq 2; then setenv BOOT_B_LEFT 1;
        else setenv BOOT_B_LEFT 0; fi
      fi
    fi
  fi
done

if test "x${exo_slot}" = "x"; then
  # Both used up (neither came up three times): start over rather than never boot again.
  echo "exolink: no slot has attempts left; resetting both to 3"
  setenv BOOT_A_LEFT 3
  setenv BOOT_B_LEFT 3
  env export -t ${kernel_addr_r} BOOT_ORDER BOOT_A_LEFT BOOT_B_LEFT
  fatwrite ${devtype} ${devnum}:1 ${kernel_addr_r} ${exo_state} ${filesize}
  reset
fi

echo "exolink: booting slot ${exo_slot} (order ${BOOT_ORDER}; left A=${BOOT_A_LEFT} B=${BOOT_B_LEFT})"
env export -t ${kernel_addr_r} BOOT_ORDER BOOT_A_LEFT BOOT_B_LEFT
fatwrite ${devtype} ${devnum}:1 ${kernel_addr_r} ${exo_state} ${filesize}

part uuid ${devtype} ${devnum}:${exo_part} exo_uuid
if test -z "${console}"; then setenv console ttyAMA0,115200; fi
setenv bootargs "root=PARTUUID=${exo_uuid} rootwait ro console=${console} rauc.slot=${exo_slot}"
load ${devtype} ${devnum}:${exo_part} ${kernel_addr_r} /boot/exolink/vmlinuz
load ${devtype} ${devnum}:${exo_part} ${ramdisk_addr_r} /boot/exolink/initrd.img
setenv exo_initrd ${ramdisk_addr_r}:${filesize}
# The BeagleBone's U-Boot names its board's dtb (fdtfile, from the EEPROM): ours is that one with
# the exolink overlay merged. qemu's virt machine hands U-Boot its own tree (fdtcontroladdr).
if test -n "${fdtfile}"; then
  load ${devtype} ${devnum}:${exo_part} ${fdt_addr_r} /boot/exolink/board.dtb
  bootz ${kernel_addr_r} ${exo_initrd} ${fdt_addr_r}
else
  bootz ${kernel_addr_r} ${exo_initrd} ${fdtcontroladdr}
fi
echo "exolink: slot ${exo_slot} did not boot"
