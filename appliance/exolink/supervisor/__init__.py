"""The supervisor: node processes, CAN link, trigger line, safety watchdog, management API."""
