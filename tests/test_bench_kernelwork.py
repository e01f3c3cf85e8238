"""The board bench's workqueue trace (benchmarks/board/kernelwork.py) read back: items paired
by worker thread, durations, and the summary's ranking. The lines are the kernel's own format
(6.1, ``workqueue_execute_start`` / ``_end``); this kernel has no tracefs to produce them."""

from __future__ import annotations

from benchmarks.board import kernelwork

TRACE = """\
# tracer: nop
#
     kworker/0:2-45      [000] d..1.  100.000000: workqueue_execute_start: work struct c1d2e3f4: function bpf_prog_free_deferred
     kworker/1:1-46      [001] d..1.  100.010000: workqueue_execute_start: work struct c1000000: function vmstat_update
     kworker/1:1-46      [001] d..1.  100.010500: workqueue_execute_end: work struct c1000000: function vmstat_update
     kworker/0:2-45      [000] d..1.  100.480000: workqueue_execute_end: work struct c1d2e3f4: function bpf_prog_free_deferred
     kworker/0:2-45      [000] d..1.  101.000000: workqueue_execute_start: work struct c1000000: function vmstat_update
     kworker/0:2-45      [000] d..1.  101.001000: workqueue_execute_end: work struct c1000000: function vmstat_update
     kworker/0:1-47      [000] d..1.  102.000000: workqueue_execute_start: work struct c2000000: function flush_to_ldisc
"""


def test_items_pair_start_and_end_by_worker_thread() -> None:
    got = kernelwork.items(TRACE)
    assert [(i["fn"], i["thread"], i["cpu"]) for i in got] == [
        ("bpf_prog_free_deferred", "kworker/0:2", 0),
        ("vmstat_update", "kworker/1:1", 1),
        ("vmstat_update", "kworker/0:2", 0),
    ]  # the item still running at the trace's end is left out
    assert [round(i["ms"], 3) for i in got] == [480.0, 0.5, 1.0]


def test_summary_ranks_functions_by_total_and_items_by_length() -> None:
    s = kernelwork.summarize(kernelwork.items(TRACE), top=2)
    assert s["items"] == 3
    assert list(s["functions"]) == ["bpf_prog_free_deferred", "vmstat_update"]
    assert s["functions"]["vmstat_update"] == {"n": 2, "total_ms": 1.5, "max_ms": 1.0}
    assert [i["fn"] for i in s["longest"]] == ["bpf_prog_free_deferred", "vmstat_update"]
    assert s["longest"][0]["t"] == 100.0


def test_arm_command_uses_the_journals_clock() -> None:
    cmd = kernelwork.arm_command()
    assert "echo mono > trace_clock" in cmd
    assert all(f"events/{e}/enable" in cmd for e in kernelwork.EVENTS)
