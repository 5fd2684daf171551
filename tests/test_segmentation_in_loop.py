"""The scan's own kidney-visible decisions judged against the simulation truth
(benchmarks/_scan_rows.py: ``segmentation_in_loop``, benchmarks only), and the recorder's
note of which frame each decision was segmented from."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from pydrake.math import RigidTransform

from benchmarks._scan_rows import (
    agreement_counts,
    in_loop_line,
    in_loop_totals,
    segmentation_in_loop,
)
from drake_rus.control.supervisor import Phase
from drake_rus.scan.diagram import FrameRecord
from drake_rus.scenario import Scenario

# An ellipsoidal true kidney (2 mm voxels), semi-axes A, B, C (m), DEPTH under the probe.
A, B, C, DEPTH = 0.030, 0.015, 0.012, 0.090


def _truth():
    g = np.mgrid[-0.03:0.03:0.002, -0.016:0.016:0.002, -0.012:0.012:0.002].reshape(3, -1).T
    inside = ((g / [A, B, C]) ** 2).sum(axis=1) <= 1
    return SimpleNamespace(kidney_points_B=g[inside] + [0, 0, DEPTH], voxel_volume=0.002**3)


def test_agreement_counts_sort_frames_by_the_true_section():
    """In view (at least the minimum area): seen or missed; no kidney at all: marked or
    not; a section under the minimum: an edge frame, either answer right."""
    areas = [2e-4, 2e-4, 0.0, 0.0, 0.0, 5e-5]
    marked = [True, False, True, False, False, True]
    counts = agreement_counts(marked, areas, 1e-4)
    assert counts == {
        "frames": 6,
        "in_view": 2,
        "missed_in_view": 1,
        "out_of_view": 3,
        "marked_out_of_view": 1,
        "edge": 1,
    }
    with pytest.raises(ValueError, match="one mark per frame expected, got 2 marks and 3"):
        agreement_counts([True, False], [0.0, 0.0, 0.0], 1e-4)


def _result(decisions, lag=0):
    """A still patient's scan: frames 0..n-1, the first half in EXPLORE over the kidney
    (probe at the origin), the second in PIVOT 50 mm beside it (no kidney in the image);
    ``decisions[k]``: the kidney_visible of frame k's segmentation, read ``lag`` frames
    later."""
    n = len(decisions)
    frames = []
    for k in range(n):
        pivot = k >= n // 2
        source = k - lag
        frames.append(
            FrameRecord(
                0.05 * k,
                k,
                int(Phase.PIVOT if pivot else Phase.EXPLORE),
                RigidTransform([0.0, 0.05 if pivot else 0.0, 0.0]),
                bool(decisions[source]) if source >= 0 else False,
                9.0,
                source,
            )
        )
    return SimpleNamespace(truth=_truth(), frames=frames, scenario=Scenario())


def test_each_decision_is_judged_at_the_pose_of_the_frame_it_came_from():
    """Explore frames over the kidney, pivot frames beside it: a missed explore frame and a
    marked pivot frame are counted in their own phase; read one frame late, each decision
    still meets its own frame's truth, and the frame read before any segmentation counts
    nothing."""
    decisions = [True, True, False, True, False, True, False, False]
    on_time = segmentation_in_loop(_result(decisions))
    assert on_time["frames"] == 8 and on_time["in_view"] == 4 and on_time["out_of_view"] == 4
    assert on_time["missed_in_view"] == 1 and on_time["marked_out_of_view"] == 1
    assert on_time["by_phase"]["explore"]["missed_in_view"] == 1
    assert on_time["by_phase"]["pivot"]["marked_out_of_view"] == 1
    late = segmentation_in_loop(_result(decisions, lag=1))
    # Frame 7's segmentation was never read; frame 3's (a kidney frame) was read in PIVOT.
    assert late["frames"] == 7 and late["in_view"] == 4 and late["missed_in_view"] == 1
    assert late["marked_out_of_view"] == 1


def test_no_verdict_without_truth_or_with_a_moving_patient():
    r = _result([True, False])
    r.truth = None
    assert segmentation_in_loop(r) is None
    r = _result([True, False])
    r.scenario.patient.motion.breathing.enabled = True
    assert segmentation_in_loop(r) is None


def test_totals_sum_the_scans_and_give_the_shares():
    one = segmentation_in_loop(_result([True, True, False, True, False, True, False, False]))
    two = segmentation_in_loop(_result([True] * 8))
    totals = in_loop_totals([{"segmentation_in_loop": one}, {"segmentation_in_loop": two}, {}])
    assert totals["scans"] == 2 and totals["in_view"] == 8 and totals["missed_in_view"] == 1
    assert totals["marked_out_of_view"] == 5 and totals["out_of_view"] == 8
    assert totals["missed_share"] == 0.125 and totals["false_mark_share"] == 0.625
    assert totals["by_phase"]["pivot"]["marked_out_of_view"] == 5
    assert "pivot missed 0 of 0 frames with the kidney in view, marked 5 of 8 with none" in (
        in_loop_line(totals)
    )
    assert in_loop_totals([{}]) is None
    assert "no truth" in in_loop_line(None)


def test_the_recorder_notes_which_frame_a_decision_came_from():
    """A segmentation running beside the loop hands its result a frame late: the record of
    frame 4 carries the decision of frame 3."""
    from pydrake.systems.analysis import Simulator

    from drake_rus.imaging.frames import UsFrame
    from drake_rus.scan.diagram import ScanRecorder

    recorder = ScanRecorder(frame_rate_hz=20.0)
    context = recorder.CreateDefaultContext()
    image = np.zeros((4, 4), np.uint8)
    recorder.GetInputPort("us_image").FixValue(context, UsFrame(image, 0.0, frame_index=4))
    recorder.GetInputPort("kidney_mask").FixValue(context, UsFrame(image, 0.0, frame_index=3))
    recorder.GetInputPort("phase").FixValue(context, [float(Phase.EXPLORE)])
    recorder.GetInputPort("kidney_visible").FixValue(context, [1.0])
    recorder.GetInputPort("contact_force").FixValue(context, [5.0])
    Simulator(recorder, context).AdvanceTo(0.1)
    assert [(f.frame_index, f.mask_frame_index, f.visible) for f in recorder.frames] == [
        (4, 3, True)
    ]


def test_the_landing_is_counted_apart():
    """A frame taken while the probe lands (APPROACH) over the kidney, unmarked: counted in
    its phase, not in the totals (the probe may not touch the skin yet)."""
    r = _result([True, True, False, False])
    r.frames[0] = dataclasses.replace(r.frames[0], phase=int(Phase.APPROACH), visible=False)
    out = segmentation_in_loop(r)
    assert out["by_phase"]["approach"]["missed_in_view"] == 1
    assert out["frames"] == 3 and out["missed_in_view"] == 0
