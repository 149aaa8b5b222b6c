"""slamkit.bench.growth: cost against map size, from the per-frame notes of a run (issue 15 item 4)."""

from __future__ import annotations

from pathlib import Path

import pytest

from slamkit.bench.growth import GrowthSample, format_growth, growth_report, plot_growth
from slamkit.errors import ConfigError


def _run(n_frames: int = 1000, kf_every: int = 5) -> tuple[list[GrowthSample], list[float]]:
    """A made-up run: a keyframe every ``kf_every`` frames, processed at once; memory 200 MiB + 0.25 MiB per
    keyframe; tracking 10 ms until frame 400 and 14 ms after; local mapping 100 ms per keyframe for the first half
    of the keyframes and 150 ms after; frames 0-4 are initialisation attempts (no tracking time)."""
    samples = []
    for i in range(n_frames):
        kf = i // kf_every + 1
        track = None if i < 5 else (10.0 if i < 400 else 14.0)
        samples.append(GrowthSample(frame_index=i, keyframes=kf, mapped=kf, rss_mb=200.0 + 0.25 * kf, track_ms=track))
    n_kf = samples[-1].mapped
    mapping_ms = [100.0 if j < n_kf // 2 else 150.0 for j in range(n_kf)]
    return samples, mapping_ms


def test_quarters_after_the_first_200_frames_compare_last_to_first_and_memory_is_the_slope() -> None:
    samples, mapping_ms = _run()
    report = growth_report(samples, mapping_ms)
    assert report is not None
    parts = report["parts"]
    assert [p["frames"] for p in parts] == [[200, 399], [400, 599], [600, 799], [800, 999]]
    assert [p["keyframes_at_end"] for p in parts] == [80, 120, 160, 200]
    # tracking: 10 ms in the first quarter, 14 ms in the last
    assert parts[0]["tracking_ms_median"] == 10.0 and parts[-1]["tracking_ms_median"] == 14.0
    assert report["tracking_last_over_first"] == pytest.approx(1.4)
    # each quarter's keyframes are those processed during it: 40 per quarter, keyframes 41-80 first
    assert [p["keyframes_mapped"] for p in parts] == [40, 40, 40, 40]
    assert parts[0]["local_mapping_ms_median"] == 100.0 and parts[-1]["local_mapping_ms_median"] == 150.0
    assert report["local_mapping_last_over_first"] == pytest.approx(1.5)
    # memory per keyframe is what each keyframe adds, not the process's fixed 200 MiB divided in
    assert report["rss_mb_per_keyframe"] == pytest.approx(0.25)
    assert report["keyframes_max"] == 200
    text = format_growth(report)
    assert "x1.40" in text and "x1.50" in text and "0.250 MiB per keyframe" in text


def test_a_keyframe_counts_in_the_part_whose_frames_saw_its_processing_end() -> None:
    """Threaded runner: a keyframe made at frame 300 whose local mapping ends at frame 420 is counted in the
    second quarter (frames 400-599), with its own time."""
    samples, _ = _run()
    samples = [GrowthSample(s.frame_index, 10, 1 if s.frame_index < 420 else 2, 300.0, 10.0) for s in samples]
    report = growth_report(samples, [50.0, 900.0])
    assert report is not None
    assert [p["keyframes_mapped"] for p in report["parts"]] == [0, 1, 0, 0]
    assert report["parts"][1]["local_mapping_ms_median"] == 900.0
    assert report["local_mapping_last_over_first"] is None  # no keyframe in the first or the last quarter
    assert report["rss_mb_per_keyframe"] is None  # the map did not grow: no slope


def test_a_run_too_short_for_the_parts_has_no_report() -> None:
    samples, mapping_ms = _run(n_frames=203)
    assert growth_report(samples, mapping_ms) is None


def test_plot_writes_a_png_and_refuses_another_suffix(tmp_path: Path) -> None:
    samples, mapping_ms = _run(n_frames=300)
    out = plot_growth(tmp_path / "growth.png", samples, mapping_ms, title="made up")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ConfigError, match=r"must end in \.png"):
        plot_growth(tmp_path / "growth.jpg", samples, mapping_ms)
