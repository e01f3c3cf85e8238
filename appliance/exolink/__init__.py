"""exolink: the exoskeleton CAN/Zenoh appliance for the BeagleBone Black."""

__version__ = "0.1.0"
