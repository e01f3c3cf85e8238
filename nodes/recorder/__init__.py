from exolink.nodes.recorder.node import Inbox, McapFile, Recorder, RecorderParams, Stats

__all__ = ["Inbox", "McapFile", "Recorder", "RecorderParams", "Stats"]
