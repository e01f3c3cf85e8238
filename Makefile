# exolink: `make sim` runs the appliance on simulated hardware, `make test` runs the tests.
# Both set everything up on a fresh machine: a venv in .venv with the locked dependencies.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml requirements.lock | cksum | cut -d' ' -f1)
PYTEST_ARGS ?=
# The layer contracts (pyproject's [tool.importlinter]) on the package as installed: exolink/ is
# appliance/exolink/ and exolink/nodes/ is nodes/. The editable install maps nodes/ by an import
# hook that import-linter cannot walk (it saw no node module), so it reads a tree of links laid out so.
IMPORT_TREE := $(VENV)/import-tree
LINT_IMPORTS = rm -rf $(IMPORT_TREE) && mkdir -p $(IMPORT_TREE)/exolink && \
	ln -s $(CURDIR)/appliance/exolink/* $(IMPORT_TREE)/exolink/ && ln -s $(CURDIR)/nodes $(IMPORT_TREE)/exolink/nodes && \
	PYTHONPATH=$(CURDIR)/$(IMPORT_TREE) $(BIN)/lint-imports
# Types (settings in pyproject's [tool.mypy]) on the same tree, after LINT_IMPORTS made it.
LINT_TYPES = MYPYPATH=$(CURDIR)/$(IMPORT_TREE) $(BIN)/mypy -p exolink
# Host apt-get waits for a dpkg lock held by another apt run instead of failing at once.
APT_WAIT := -o DPkg::Lock::Timeout=600

.PHONY: install sim dist test browser uboot test-kernel test-image image bundle image-lock test-image-built test-update overlays lint format bench bench-board lock dbc msgs clean

install: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	@test -x $(BIN)/python || $(PY) -m venv $(VENV) || { \
	  echo "python venv missing: installing python3-venv"; \
	  apt-get $(APT_WAIT) update -qq && apt-get $(APT_WAIT) install -y -qq python3-venv && $(PY) -m venv $(VENV); }
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c requirements.lock -e '.[dev]'
	rm -f $(VENV)/.installed-* && touch $@

# CONFIG=<file>: another appliance on simulated hardware, e.g. a lab's own device
# (tests/lab_rig/rig.yaml, after `.venv/bin/pip install tests/lab_rig`).
sim: $(STAMP)
	$(BIN)/exolink up --sim $(if $(CONFIG),-c $(CONFIG))

# The wheel and sdist in dist/: `pipx install dist/exolink-*.whl` gives a laptop the CLI alone
# (tests/test_dist.py checks the wheel's entry point and package data).
dist: $(STAMP)
	rm -rf dist
	$(BIN)/python -m build --outdir dist .
	@echo "laptop: pipx install $$(ls dist/exolink-*.whl)"

# Debian's chromium: the dashboard's browser tests drive it (tests/test_dashboard.py, playwright).
browser:
	@command -v chromium >/dev/null || { echo "chromium missing: installing Debian's"; \
	  apt-get $(APT_WAIT) update -qq && apt-get $(APT_WAIT) install -y -qq chromium; }

# Debian's qemu_arm U-Boot and the card tools: tests/test_bootscript.py runs the card's boot script
# in U-Boot under qemu (it skips, saying what is missing, without them).
uboot:
	bash image/need.sh qemu-system-arm:qemu-system-arm mkimage:u-boot-tools mkfs.vfat:dosfstools \
	  mcopy:mtools mtype:mtools mkfs.ext4:e2fsprogs sfdisk:fdisk
	@test -f /usr/lib/u-boot/qemu_arm/u-boot.bin || { echo "u-boot-qemu missing: installing Debian's"; \
	  apt-get $(APT_WAIT) update -qq && apt-get $(APT_WAIT) install -y -qq u-boot-qemu; }

test: $(STAMP) browser uboot
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(LINT_IMPORTS)
	$(LINT_TYPES)
	$(BIN)/python -m pytest $(PYTEST_ARGS)

# Kernel-level tests (SocketCAN in User-Mode Linux, gpio-sim in qemu): see tests/kernel/run.sh.
test-kernel: $(STAMP)
	bash tests/kernel/run.sh

# Device-tree overlay and image checks (dtc from Debian's device-tree-compiler).
overlays: build/overlays/exolink-dcan1.dtbo

build/overlays/%.dtbo: overlays/%.dts
	@command -v dtc >/dev/null || { apt-get $(APT_WAIT) update -qq && apt-get $(APT_WAIT) install -y -qq device-tree-compiler; }
	mkdir -p $(@D) && dtc -@ -q -I dts -O dtb -o $@ $<

test-image: $(STAMP) overlays
	EXOLINK_REQUIRE_IMAGE=1 $(BIN)/python -m pytest -q -rs tests/image/test_overlay.py tests/image/test_recipe.py

# The flashable SD-card image (root, ~20 min here): build/image/exolink-bbb-<version>.img.xz.
image: $(STAMP) overlays
	bash image/build.sh

# A signed RAUC update bundle of the same root (root, ~10 min with the image's cached base):
# build/image/exolink-bbb-<version>.raucb; `exolink update` sends it to a board. The signing key:
# RAUC_KEY / RAUC_CERT / RAUC_KEYRING, else a development pair made once in build/rauc/.
bundle: $(STAMP) overlays
	bash image/build.sh bundle

# Pin the Debian package set of the last build (commit image/debian.lock).
image-lock:
	cp "$$(ls -t build/image/exolink-bbb-*.packages | head -1)" image/debian.lock

# Checks of the built image: layout, boot files, units, and a qemu boot to a running supervisor.
test-image-built: $(STAMP)
	bash image/need.sh qemu-system-arm:qemu-system-arm sfdisk:fdisk mcopy:mtools debugfs:e2fsprogs \
	  fdtget:device-tree-compiler
	EXOLINK_REQUIRE_IMAGE=1 $(BIN)/python -m pytest -q -rs -p no:cacheprovider tests/image/test_built_image.py

# A/B updates under qemu through U-Boot (the built image and bundle; ~40 min): A -> B kept, B whose
# supervisor cannot start -> back on A by itself, a bundle with a bad signature refused.
test-update: $(STAMP)
	bash image/need.sh qemu-system-arm:qemu-system-arm sfdisk:fdisk mcopy:mtools debugfs:e2fsprogs \
	  rauc:rauc mksquashfs:squashfs-tools
	test -f /usr/lib/u-boot/qemu_arm/u-boot.bin || { apt-get $(APT_WAIT) update -qq && apt-get $(APT_WAIT) install -y -qq u-boot-qemu; }
	EXOLINK_REQUIRE_IMAGE=1 $(BIN)/python -m pytest -q -rs -p no:cacheprovider tests/image/test_update.py

lint: $(STAMP)
	$(BIN)/ruff check . && $(BIN)/ruff format --check .
	$(LINT_IMPORTS)
	$(LINT_TYPES)

format: $(STAMP)
	$(BIN)/ruff format . && $(BIN)/ruff check --fix .

bench: $(STAMP)
	$(BIN)/python -m benchmarks --out bench-results.json

# Board proxy: a copy of the built card (make image) running this checkout's code under
# qemu-system-arm (TCG) with the nominal load, then the same natively; ~6 min when the image exists.
# Table on stdout, JSON in build/bench-board.json (BENCH_BOARD_ARGS=--help for the options).
BENCH_BOARD_ARGS ?=
bench-board: $(STAMP)
	bash image/need.sh qemu-system-arm:qemu-system-arm sfdisk:fdisk mcopy:mtools \
	  debugfs:e2fsprogs ssh:openssh-client ssh-keygen:openssh-client taskset:util-linux
	$(BIN)/python -m benchmarks.board $(BENCH_BOARD_ARGS)

# Regenerate the pinned set after editing dependencies in pyproject.toml.
lock:
	rm -rf /tmp/exolink-lock && $(PY) -m venv /tmp/exolink-lock
	/tmp/exolink-lock/bin/pip install -q '.[dev]'
	/tmp/exolink-lock/bin/pip freeze --exclude-editable | grep -v '^exolink' > requirements.lock

dbc: $(STAMP)
	$(BIN)/python -m exolink.protocol.make_dbc

# Regenerate appliance/exolink/msgs/type_hashes.json after editing a .msg file (checked by the tests).
msgs: $(STAMP)
	$(BIN)/python -c 'from exolink import messaging; print(messaging.write_hash_table(), "types")'

clean:
	rm -rf $(VENV) build dist *.egg-info bench-results.json
