"""``one_thread``: Open3D's thread count is one process-wide setting, so sections that overlap (two
threads of a server estimating at once, a nested call) must not undo each other: every section runs
on one thread, and the count from before comes back only when the last section leaves."""

from __future__ import annotations

import threading
from contextlib import AbstractContextManager

from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.evaluation.agents import one_thread
from brave6d.evaluation.agents.pointclouds import open3d


def _threads() -> int:
    return int(open3d().utility.get_max_threads())


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 5).flatmap(lambda n: st.tuples(st.just(n), st.permutations(range(n)))))
def test_overlapping_sections_each_run_on_one_thread_and_the_last_restores(case: tuple[int, list[int]]) -> None:
    """n sections entered in order and left in any order (as threads would): one thread inside every
    section while any is open, the count from before after the last leaves (the old switch restored
    it when the first section left, under a section still running)."""
    n, exit_order = case
    before = _threads()
    sections: list[AbstractContextManager[None]] = [one_thread() for _ in range(n)]
    for section in sections:
        section.__enter__()
        assert _threads() == 1
    for left, index in enumerate(exit_order, start=1):
        sections[index].__exit__(None, None, None)
        assert _threads() == (before if left == n else 1), (exit_order, left)
    assert _threads() == before


def test_threads_that_overlap_see_one_thread_throughout() -> None:
    before = _threads()
    inside = threading.Barrier(2)
    seen: list[int] = []

    def work(wait_s: float) -> None:
        with one_thread():
            inside.wait(timeout=10)  # both sections are open now
            threading.Event().wait(wait_s)  # the first leaves while the second still runs
            seen.append(_threads())

    workers = [threading.Thread(target=work, args=(w,)) for w in (0.0, 0.2)]
    for w in workers:
        w.start()
    for w in workers:
        w.join(timeout=20)
    assert seen == [1, 1] and _threads() == before


def test_an_error_inside_a_section_still_restores_the_count() -> None:
    before = _threads()
    try:
        with one_thread():
            raise ValueError("inside")
    except ValueError:
        pass
    assert _threads() == before


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 5).flatmap(lambda n: st.tuples(st.just(n), st.permutations(range(n)))))
def test_opencvs_switch_shares_the_same_rule(case: tuple[int, list[int]]) -> None:
    """calibration's opencv_one_thread, the same mechanism (core.process_setting.HeldSetting) over
    OpenCV's thread count: one thread while any section is open, the count from before after the last."""
    import cv2

    from brave6d.calibration.opencv_threads import opencv_one_thread

    n, exit_order = case
    before = cv2.getNumThreads()
    sections = [opencv_one_thread() for _ in range(n)]
    for section in sections:
        section.__enter__()
        assert cv2.getNumThreads() == 1
    for left, index in enumerate(exit_order, start=1):
        sections[index].__exit__(None, None, None)
        assert cv2.getNumThreads() == (before if left == n else 1), (exit_order, left)
