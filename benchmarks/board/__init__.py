"""``make bench-board``: the SD-card image under qemu-system-arm as a board proxy (see README)."""
