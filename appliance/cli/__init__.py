"""The exolink command line."""
