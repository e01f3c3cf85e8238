"""Plugin nodes shipped with exolink; each registers in the ``exolink.nodes`` entry-point group."""
