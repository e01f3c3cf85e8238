"""Recordings into the gait lab's tools: C3D (analog channels + gait events) and OpenSim files.

One trial is built from an MCAP recording (``build_trial``) and written by the writers below
(``write_c3d``, ``write_opensim``, ``write_events_csv``). The rules, also in
docs/gaitlab/README.md:

Uniform clock. All channels go onto one clock at the H2's recorded rate (the median interval of
``joint_states``, rounded to a whole Hz: 100 Hz from the 10 ms stream). Time zero is the first
trigger edge (``zero="first-trigger"``, when the file has one; what was recorded before it is
not exported) or the first joint sample (``zero="start"``); frame k is at zero + k / rate.

Resampling: nearest recorded sample, never interpolated. Each clock tick takes the value of the
stream's sample nearest in time (so a value in the export is always one that was measured, at
most 0.75 of the stream's period from where it is shown; half a period on a steady stream). Foot switches and battery are published on
change (and refreshed every ``foot_switches_refresh_s``): they are states and are held, each
tick taking the last state published at or before it.

Losses are NaN, never filled. A stream's gap is an interval longer than 1.5 of its periods (the
h2 reader's own ``GapCounter`` rule): ticks inside it farther than 0.75 period from a sample
are NaN, and the frames lost are counted as that rule counts them. A MACCEPA frame the board's
cycle missed (its ``stale`` bit) is NaN for that frame's fields. Foot switches and battery are
NaN where the H2 stream has a gap (they come in the same 10 ms CAN cycle) and where their
messages stopped longer than 1.5 refresh periods. The recorder's own dropped count and any
``recover`` losses from the file's metadata are carried into the export's summary.

Gait events, per side, from the recorded foot-switch messages (the frames' own kernel times,
not the clock ticks): contact = heel OR toe. Foot Strike at contact 0 -> 1, Foot Off at 1 -> 0;
a new contact state counts only once it has held for ``debounce_s`` (default 30 ms, three H2
cycles), and the event is at the time of its first frame. A transition right after an H2 gap
(its moment is unknown) is not an event; it is counted instead.

OpenSim: joint angles in degrees, columns as the Rajagopal 2015 and gait2392 models name them.
H2 angles are hip flexion +, knee flexion +, ankle dorsiflexion + (shared/protocol/h2-can.md);
Rajagopal's knee_angle is flexion + as well, gait2392's is flexion - (``model="gait2392"``
negates the knee). Torques: the joint's N·m in the same sign as its angle, columns
``<coordinate>_moment`` as OpenSim's inverse dynamics writes them.
"""

from exolink.gaitlab.c3d import MissingExtra, require_ezc3d, samples_per_frame, write_c3d
from exolink.gaitlab.events_csv import write_events_csv
from exolink.gaitlab.model import DEBOUNCE_S, RESAMPLING, Channel, Event, Stream, Trial
from exolink.gaitlab.opensim import MODELS, write_opensim
from exolink.gaitlab.resample import foot_events, hold, nearest
from exolink.gaitlab.trial import ZERO_CHOICES, build_trial, read_streams

__all__ = [
    "DEBOUNCE_S",
    "MODELS",
    "RESAMPLING",
    "ZERO_CHOICES",
    "Channel",
    "Event",
    "MissingExtra",
    "Stream",
    "Trial",
    "build_trial",
    "foot_events",
    "hold",
    "nearest",
    "read_streams",
    "require_ezc3d",
    "samples_per_frame",
    "write_c3d",
    "write_events_csv",
    "write_opensim",
]
