"""Formats on the wire, below the Zenoh layer: CDR payloads (cdr), the ROS 2 service types
(srvtypes) and the ROS graph's names, tokens and GIDs (rosgraph)."""
