"""Recordings as files: what one still holds (check), reading it back (readback), and the
board's store that laptops list, fetch and delete over the network (store)."""
