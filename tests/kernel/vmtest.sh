#!/bin/bash
# exolink's kernel-test harness (grown from shared/tools/vmtest.sh; owned here, used by run.sh).
# vmtest.sh - run a command inside a throwaway Linux guest that has real SocketCAN (vcan, can-raw,
# can-bcm, can-gw) and, for the qemu guest, a real gpio-sim chip. The guest sees the host file system
# (read-only, with a tmpfs overlay for qemu); WORKDIR is shared read-write at the same path. The guest
# has no network except loopback. The exit status is the command's own.
#
#   vmtest.sh setup               # install host packages and build the guests (idempotent, ~30-60 s)
#   vmtest.sh qemu WORKDIR CMD    # QEMU/TCG guest: CAN + gpio-sim (slow CPU: ~10-15x)
#   vmtest.sh uml  WORKDIR CMD    # User-Mode Linux: CAN only (no GPIOLIB in Debian's UML), near-native
#
# Env: VMDIR (default ~/.cache/exolink-vmtest), VM_KERNEL_SUITE (trixie-backports), VM_MEM, VM_CPUS,
#      VM_TIMEOUT (s), VM_ACCEL (tcg; kvm does NOT work on PVM-type /dev/kvm hosts),
#      VM_UML_DISK (a host file the UML guest sees as /dev/ubdb, with vfat loadable).
set -euo pipefail
SELF=$(realpath "$0")
VMDIR=${VMDIR:-$HOME/.cache/exolink-vmtest}
CAN_MODS="vcan can-raw can-bcm can-gw"

setup() {
  mkdir -p "$VMDIR"; cd "$VMDIR"
  local need=()
  command -v qemu-system-x86_64 >/dev/null || need+=(qemu-system-x86)
  [ -x /usr/bin/linux.uml ] || need+=(user-mode-linux)
  [ -x /bin/busybox ] && /bin/busybox --list | grep -qx switch_root || need+=(busybox-static)
  command -v depmod >/dev/null || need+=(kmod)
  command -v ip >/dev/null || need+=(iproute2)
  command -v cpio >/dev/null || need+=(cpio)
  command -v mtype >/dev/null || need+=(mtools)
  command -v mkfs.vfat >/dev/null || need+=(dosfstools)
  if [ ${#need[@]} -gt 0 ]; then
    apt-get -o DPkg::Lock::Timeout=600 update -qq
    DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  fi
  # UML: modules ship with modules.dep under /usr/lib/uml/modules/<ver>; give modprobe -d a lib/modules view
  local uv; uv=$(ls /usr/lib/uml/modules | head -1)
  mkdir -p uml/lib/modules; ln -sfn "/usr/lib/uml/modules/$uv" "uml/lib/modules/$uv"

  # QEMU guest kernel: Debian 7.x amd64 kernel (bookworm's 6.1 and trixie's 6.12 lack CONFIG_GPIO_SIM)
  if [ ! -f qemu/kernel.ready ]; then
    local suite=${VM_KERNEL_SUITE:-trixie-backports} A=qemu/apt
    rm -rf qemu; mkdir -p $A/lists/partial $A/cache/archives/partial qemu/debs qemu/x
    local mirror   # the Debian mirror this machine already uses (no host name is written here)
    mirror=$(awk '/^URIs:/{print $2; exit} /^deb /{print $2; exit}' /etc/apt/sources.list.d/debian.sources /etc/apt/sources.list 2>/dev/null | head -1)
    echo "deb [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] $mirror $suite main" > $A/sources.list
    local APTO=(-o Dir::Etc::sourcelist="$VMDIR/$A/sources.list" -o Dir::Etc::sourceparts=/nonexistent
                -o Dir::State::Lists="$VMDIR/$A/lists" -o Dir::Cache="$VMDIR/$A/cache"
                -o Debug::NoLocking=1 -o APT::Sandbox::User=root)
    apt-get "${APTO[@]}" -qq update          # private apt state: the host's sources/lists are untouched
    local img pkgs
    img=$(apt-cache "${APTO[@]}" depends linux-image-amd64 | awk '/Depends: linux-image-[0-9]/{print $2; exit}')
    pkgs=$(apt-cache "${APTO[@]}" depends "$img" | awk '/Depends: linux-(base|binary|modules)-[0-9]/{print $2}' | sort -u)
    [ -n "$pkgs" ] || pkgs=$img              # pre-7.x packaging: all in linux-image-*
    (cd qemu/debs && apt-get "${APTO[@]}" -qq download $pkgs)
    for d in qemu/debs/*.deb; do
      dpkg-deb --fsys-tarfile "$d" | tar -x -C qemu/x --wildcards '*/vmlinuz*' '*/config*' \
        '*/modules.order' '*/modules.builtin*' '*/kernel/net/can/*' '*/kernel/drivers/net/can/*' \
        '*/kernel/drivers/gpio/gpio-sim.ko*' '*/kernel/fs/configfs/*' '*/kernel/fs/9p/*' \
        '*/kernel/net/9p/*' '*/kernel/fs/netfs/*' '*/kernel/fs/overlayfs/*' 2>/dev/null || true
    done
    local md kv cfg
    md=$(dirname "$(find qemu/x -path '*/modules/*/modules.order' | head -1)"); kv=$(basename "$md")
    cfg=$(find qemu/x \( -name config -o -name "config-$kv" \) -type f | head -1)
    for c in CAN_VCAN CAN_RAW CAN_BCM GPIO_SIM CONFIGFS_FS GPIO_CDEV; do
      grep -qE "^CONFIG_$c=[ym]" "$cfg" || { echo "vmtest: kernel $kv lacks CONFIG_$c" >&2; exit 1; }
    done
    mv "$(find qemu/x -name 'vmlinuz*' -type f | head -1)" qemu/vmlinuz
    mkdir -p qemu/mods/lib/modules; mv "$md" qemu/mods/lib/modules/; depmod -b "$VMDIR/qemu/mods" "$kv"
    rm -rf qemu/x qemu/debs "$A/cache"; echo "$kv" > qemu/kver; touch qemu/kernel.ready
  fi
  # initramfs: static busybox + 9p/overlay modules; mounts host / (9p, ro) + tmpfs overlay, then the workdir rw
  local kv; kv=$(cat qemu/kver); rm -rf qemu/initrd; mkdir -p qemu/initrd/{bin,mods,proc,sys,dev,lower,ovl,newroot}
  cp /bin/busybox qemu/initrd/bin/
  for m in netfs 9pnet 9pnet_virtio 9p overlay; do
    f=$(find "qemu/mods/lib/modules/$kv" -name "$m.ko*" | head -1); [ -n "$f" ] || continue
    case $f in *.xz) xz -dc "$f";; *.zst) zstd -dc "$f";; *) cat "$f";; esac > "qemu/initrd/mods/$m.ko"
  done
  cat > qemu/initrd/init <<'INIT'
#!/bin/busybox sh
/bin/busybox --install -s /bin; export PATH=/bin
mount -t proc proc /proc; mount -t sysfs sysfs /sys; mount -t devtmpfs devtmpfs /dev
for m in netfs 9pnet 9pnet_virtio 9p overlay; do [ -f /mods/$m.ko ] && insmod /mods/$m.ko; done
for a in $(cat /proc/cmdline); do case $a in vmt.work=*) W=${a#vmt.work=};; vmt.init=*) I=${a#vmt.init=};; esac; done
o=trans=virtio,version=9p2000.L,msize=512000
mount -t 9p -o $o,cache=loose,ro rootfs /lower || { echo "vmtest: cannot mount host /"; poweroff -f; }
mount -t tmpfs -o mode=755 tmpfs /ovl; mkdir /ovl/u /ovl/w
mount -t overlay -o lowerdir=/lower,upperdir=/ovl/u,workdir=/ovl/w overlay /newroot
mount -t tmpfs -o mode=755 tmpfs /newroot/run
mkdir -p /newroot$W; mount -t 9p -o $o work /newroot$W
for d in proc sys dev; do mount --move /$d /newroot/$d; done
exec switch_root /newroot /bin/bash $I __guest
INIT
  chmod +x qemu/initrd/init
  (cd qemu/initrd && find . | cpio -o -H newc --quiet | gzip -1) > qemu/initrd.img
  echo "vmtest: ready in $VMDIR (qemu kernel $kv, uml $uv)"
}

guest() {   # PID 1 inside either guest
  set +eu
  export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin HOME=/root
  # UML's hostfs root shows the HOST's /proc and /sys until the guest mounts its own: mount them first
  mount -t proc proc /proc
  local W M K a
  for a in $(cat /proc/cmdline); do case $a in vmt.work=*) W=${a#vmt.work=};; vmt.mods=*) M=${a#vmt.mods=};; vmt.kind=*) K=${a#vmt.kind=};; esac; done
  if [ "$K" = uml ]; then mount -t sysfs sysfs /sys; mount -t devtmpfs devtmpfs /dev 2>/dev/null; fi
  mkdir -p /dev/pts /dev/shm 2>/dev/null; mount -t devpts devpts /dev/pts; mount -t tmpfs tmpfs /dev/shm
  [ "$K" = uml ] && mount -t tmpfs tmpfs /run
  if [ "$K" = uml ]; then mount -t hostfs -o "$W" none "$W"; else
    mkdir -p /lib/modules && ln -s "$M/lib/modules/$(uname -r)" /lib/modules/; fi   # plain modprobe works (qemu)
  for m in $CAN_MODS $([ "$K" = qemu ] && echo configfs gpio-sim) \
      $([ "$K" = uml ] && echo vfat nls_cp437 nls_iso8859-1); do modprobe -d "$M" "$m"; done
  mountpoint -q /sys/kernel/config || mount -t configfs none /sys/kernel/config 2>/dev/null || true
  ip link set lo up; hostname "vmtest-$K"
  cd "$W"; bash "$W/.vmtest/cmd" </dev/null; local rc=$?
  echo "$rc" > "$W/.vmtest/rc"; sync
  grep -q vmt.kind= /proc/cmdline && echo o > /proc/sysrq-trigger; sleep 5; poweroff -f   # guard: never the host's /proc
}

run() {
  local kind=$1 W; W=$(realpath "$2"); shift 2
  mkdir -p "$W/.vmtest"; rm -f "$W/.vmtest/rc"; printf '%s\n' "$*" > "$W/.vmtest/cmd"
  local args="vmt.kind=$kind vmt.work=$W"
  if [ "$kind" = qemu ]; then
    timeout "${VM_TIMEOUT:-1800}" qemu-system-x86_64 -accel "${VM_ACCEL:-tcg}" -cpu max \
      -smp "${VM_CPUS:-1}" -m "${VM_MEM:-2G}" -display none -monitor none -serial stdio -no-reboot -nic none \
      -kernel "$VMDIR/qemu/vmlinuz" -initrd "$VMDIR/qemu/initrd.img" \
      -append "console=ttyS0 quiet loglevel=3 panic=-1 $args vmt.mods=$VMDIR/qemu/mods vmt.init=$SELF" \
      -fsdev local,id=r,path=/,security_model=none,readonly=on,multidevs=remap -device virtio-9p-pci,fsdev=r,mount_tag=rootfs \
      -fsdev local,id=w,path="$W",security_model=none,multidevs=remap -device virtio-9p-pci,fsdev=w,mount_tag=work </dev/null || true
  else
    timeout "${VM_TIMEOUT:-1800}" /usr/bin/linux.uml mem="${VM_MEM:-1G}" root=/dev/root rootfstype=hostfs \
      rootflags=/ ro con=null con0=null,fd:1 quiet ${VM_UML_DISK:+ubdb=$VM_UML_DISK} $args vmt.mods="$VMDIR/uml" init=/bin/bash -- "$SELF" __guest </dev/null || true
  fi
  [ -s "$W/.vmtest/rc" ] || { echo "vmtest: guest gave no exit code (crash/timeout)" >&2; return 125; }
  return "$(cat "$W/.vmtest/rc")"
}

case "${1:-}" in
  setup) setup ;;
  qemu|uml) [ $# -ge 3 ] || { echo "usage: $0 $1 WORKDIR CMD..." >&2; exit 2; }; run "$@" ;;
  __guest) guest ;;
  *) sed -n '2,14p' "$SELF"; exit 2 ;;
esac
