"""MCAP recorder [thesis: rosbag record and the GUIs' text logs].

Records every topic the ROS graph shows a publisher of (or a configured subset; see ``Inbox``;
batched 100 Hz topics come as bundles) and writes MCAP files with ``ros2msg`` schemas and the
CDR payloads exactly as they travelled, so rosbag2, Foxglove and PlotJuggler open them.
Samples wait in Zenoh's ring channel (the inbox, ``params.inbox`` per subscription) until the
node's loop takes them in batches every ``INTAKE_PERIOD_S``: no Python runs on Zenoh's thread
per sample (a callback took the GIL for each; on the board a writer thread woken per sample was
half the recorder's CPU). A sample's log time is when the loop took it (up to
``INTAKE_PERIOD_S`` after it arrived); its publish time is the publisher's stamp.
A slow SD card never stalls the session; the inbox holds ~90 s of data. Nothing is lost
silently: every appliance publisher numbers its samples, so a sample that never arrived or that
the full ring let go (the oldest go first) is a gap in its publisher's sequence, counted as
dropped. The counters go out on diagnostics (which are recorded too) and into each file's
``exolink.stats`` metadata.
Subscribed only while recording: an idle recorder (no ``autostart``, or stopped) takes no sample
at all, rather than taking each one to drop it.
What the bus readers lost before anything reached Zenoh goes into ``exolink.receive``: each
reader's receive counters (its ``nodes/<name>/stats``) when the file was opened and closed.
Every ``fsync_interval_s`` the chunk in progress is closed and the file fsynced: power loss costs
at most that much. The card is checked every second: under ``reserve_mb`` free, the recording
stops cleanly (the file closed and indexed) with an ERROR diagnostic ("card full"), and no new
one starts, so the card never fills and nothing else on the board (logs, the journal) fails for
it. A disk full all the same (a smaller reserve than one second of data, another writer) stops
it too; earlier files are never reopened.
The recorder also serves its directory to laptops (``recordings``: exolink.recordings.store): it alone
knows which file it is writing, and that one is never handed out nor deleted.

- ``node``: the node: commands, the writer loop, diagnostics, receive counters;
- ``intake``: what it takes from the inbox: keys parsed once, bundles opened, gaps counted;
- ``inbox``: what it subscribes to, learnt from the ROS 2 graph, and the topic budgets;
- ``mcapfile``: the MCAP file writer;
- ``params``: its params and its counters.
"""

from exolink.nodes.recorder.inbox import Inbox
from exolink.nodes.recorder.mcapfile import McapFile
from exolink.nodes.recorder.node import Recorder
from exolink.nodes.recorder.params import RecorderParams, Stats

__all__ = ["Inbox", "McapFile", "Recorder", "RecorderParams", "Stats"]
