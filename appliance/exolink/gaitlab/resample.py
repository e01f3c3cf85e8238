"""Recorded streams onto the trial's clock (``nearest`` sample, ``hold`` of states) and the
gait events from the foot switches (``foot_events``)."""

from __future__ import annotations

from typing import Any

from exolink.gaitlab.model import (
    DEBOUNCE_S,
    FOOT_OFF,
    FOOT_STRIKE,
    GAP_FACTOR,
    SIDES,
    Event,
    Stream,
)

# --- resampling ---------------------------------------------------------------------------------


def nearest(t: Any, v: Any, grid: Any, period_ns: float) -> Any:
    """Each tick of ``grid`` takes the sample of (t, v) nearest in time, NaN where the nearest
    is more than GAP_FACTOR / 2 periods away: inside a gap (two samples more than GAP_FACTOR
    periods apart) and past the stream's ends. Never an interpolated value."""
    import numpy as np  # lazy: the gaitlab extra (numpy: not on the board)

    out = np.full(len(grid), np.nan)
    if len(t) == 0:
        return out
    nxt = np.searchsorted(t, grid, side="left").clip(0, len(t) - 1)
    prv = (nxt - 1).clip(0, len(t) - 1)
    d_prev = np.abs(grid - t[prv])
    d_next = np.abs(t[nxt] - grid)
    idx = np.where(d_next < d_prev, nxt, prv)
    dist = np.minimum(d_prev, d_next)
    out = v[idx].astype(np.float64)
    out[dist > GAP_FACTOR * period_ns / 2] = np.nan  # in a gap, or past the ends
    return out


def hold(t: Any, v: Any, grid: Any, max_age_ns: float) -> Any:
    """Each tick takes the last state published at or before it (states published on change);
    NaN before the first and where the last is older than ``max_age_ns`` (messages stopped)."""
    import numpy as np  # lazy: the gaitlab extra

    i = np.searchsorted(t, grid, side="right") - 1
    out = np.where(i >= 0, v[i.clip(0)], np.nan).astype(np.float64)
    age = grid - t[i.clip(0)]
    out[(i < 0) | (age > max_age_ns)] = np.nan
    return out


# --- events -------------------------------------------------------------------------------------


def foot_events(
    feet: Stream, side: str, debounce_s: float = DEBOUNCE_S, joints: Stream | None = None
) -> tuple[list[Event], int]:
    """Foot Strike / Foot Off of one side (``r`` or ``l``) from its heel and toe switches (the
    rule is in the package's docstring). Returns the events and how many transitions were not
    events because they came right after an H2 gap."""
    t = feet.t
    contact = (feet.columns[f"{side}_heel"] > 0) | (feet.columns[f"{side}_toe"] > 0)
    heel = feet.columns[f"{side}_heel"] > 0
    toe = feet.columns[f"{side}_toe"] > 0
    debounce = int(debounce_s * 1e9)
    events: list[Event] = []
    skipped = 0
    state = bool(contact[0]) if len(t) else False
    js_t = joints.t if joints is not None else None
    js_gap = GAP_FACTOR * joints.period_ns() if joints is not None else 0.0
    k = 1
    while k < len(t):
        if bool(contact[k]) == state:
            k += 1
            continue
        # a change: does the new state hold for the debounce time?
        j = k
        while j + 1 < len(t) and bool(contact[j + 1]) == bool(contact[k]):
            j += 1
        end = t[j + 1] if j + 1 < len(t) else t[-1]
        if end - t[k] < debounce and j + 1 < len(t):
            k = j + 1  # a blip: ignored with its way back
            continue
        state = bool(contact[k])
        if js_t is not None and _after_gap(js_t, int(t[k]), js_gap):
            skipped += 1
        else:
            label = FOOT_STRIKE if state else FOOT_OFF
            at = k if state else k - 1  # the switches on at contact, or the last on before off
            which = " and ".join(w for w, on in (("heel", heel[at]), ("toe", toe[at])) if on)
            what = f"{which} first on" if state else f"{which} last off"
            events.append(Event(int(t[k]), label, SIDES[side], what))
        k = j + 1
    return events, skipped


def _after_gap(js_t: Any, at_ns: int, gap_ns: float) -> bool:
    """Is ``at_ns`` the first H2 news after a gap (the change happened somewhere in it)?"""
    import numpy as np  # lazy: the gaitlab extra

    i = int(np.searchsorted(js_t, at_ns, side="left"))
    if i == 0:
        return True
    return bool(at_ns - js_t[i - 1] > gap_ns)
