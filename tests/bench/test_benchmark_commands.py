"""The command benchmark (``benchmarks/commands.py``) runs on a tiny dataset, so it cannot rot.

It runs ``ptp calibrate`` in a fresh process as the user does and reports the child's own
rusage beside the read floor measured in the same run.
"""

from __future__ import annotations

import pytest

synth = pytest.importorskip("benchmarks.synth")
commands = pytest.importorskip("benchmarks.commands")


def test_command_benchmark_runs_the_cli_in_a_fresh_process(tmp_path):
    rig = synth.make_rig(0.02, 5, steps=(4, 4, 4))  # 160 x 128 px, 5 positions, 24 frames each
    data = synth.write_dataset(tmp_path / "tiny", rig)
    res = commands.measure(data, ["calibrate-poly"], repeat=1, floor_repeat=1)
    r = res["commands"]["calibrate-poly"]
    assert r["returncode"] == 0 and "worst pixels" in " ".join(r["tail"])  # the LUT summary's last lines
    # The child's own rusage: a Python process with numpy and OpenCV is > 30 MB, this one < 2 GB.
    assert 30 < r["maxrss_mb"] < 2000 and r["cpu_s"] > 0
    assert 0 < res["floor_s"] <= min(res["floors_s"]) + 1e-12
    assert r["ratio"] == pytest.approx(r["wall_s"] / res["floor_s"])
    assert r["cpu_ratio"] == pytest.approx(r["cpu_s"] / res["floor_cpu_s"])
    assert len(res["load"]) == 2


def test_unknown_command_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        commands.main([str(tmp_path), "--commands", "calibrate,nonsense"])
    assert "nonsense" in capsys.readouterr().err


@pytest.mark.slow
def test_decode_and_the_wizards_jobs_run_in_fresh_processes(tmp_path):
    """``ptp decode`` and the wizard's Acquire + Calibrate jobs (offscreen) in the command benchmark."""
    import json

    rig = synth.make_rig(0.02, 5, steps=(4, 4, 4))
    data = synth.write_dataset(tmp_path / "tiny", rig)
    res = commands.measure(data, ["decode", "wizard"], repeat=1, floor_repeat=1)
    for name in ("decode", "wizard"):
        r = res["commands"][name]
        assert r["returncode"] == 0 and 30 < r["maxrss_mb"] < 2000 and r["cpu_s"] > 0, (name, r["tail"])
    line = next(t for t in res["commands"]["wizard"]["tail"] if t.startswith("{"))
    jobs = json.loads(line)
    assert jobs["acquire"]["outcome"] == jobs["calibrate"]["outcome"] == "finished"
    assert jobs["calibrate"]["ticks"] > 0 and jobs["calibrate"]["max_gap_ms"] > 0


def test_decode_stages_benchmark_runs_on_a_tiny_dataset(tmp_path):
    """``benchmarks.decode_stages``: every stage of a tiny decode is timed, and the patches undone."""
    decode_stages = pytest.importorskip("benchmarks.decode_stages")
    rig = synth.make_rig(0.005, 2, steps=(4, 4, 8))  # 80 x 64 px, 2 positions (the first warms up)
    data = synth.write_dataset(tmp_path / "tiny", rig)
    recipe = decode_stages.recipe_module()
    before = recipe.wrapped_phase
    res = decode_stages.measure(data, [0, 1], "gzip")
    assert recipe.wrapped_phase is before
    assert res["positions"] == 1 and res["frames"] == 32 and res["file_mb_per_position"] > 0
    stages = res["stages"]
    for label in ("N-step sums (wrapped_phase)", "spatial check (spatial_outliers)", "the file (gzip)"):
        assert stages[label][1] > 0 and stages[label][0] >= 0
    assert stages["spatial check (spatial_outliers)"][1] == 2  # one position, two directions
