"""The board as a machine: its settings from the card (setup), its wall clock (clock) and its
A/B root file system updates (update)."""
