"""benchmarks/acceptance_must_show.py's table: the median over seeds of each ratio against issue 35's bounds."""

from benchmarks.acceptance_must_show import BOUNDS, table


def _run(preset, seed, **ratio):
    return {"preset": preset, "seed": seed, "ratio": ratio}


def test_medians_and_verdicts():
    runs = [_run("scanner-rough", s, SD=sd, PS=0.3, PF=1.0, F=1.2) for s, sd in enumerate((0.2, 0.9, 0.4))]
    lines = {tuple(line.split()[:2]): line for line in table(runs).splitlines()[1:]}
    assert lines[("scanner-rough", "SD")].split()[2] == "0.400" and lines[("scanner-rough", "SD")].endswith("holds")
    assert "0.20..0.90" in lines[("scanner-rough", "SD")]
    assert lines[("scanner-rough", "F")].endswith("FAILS")  # 1.2 > 1.1
    assert BOUNDS["scanner-mild"]["PS"] == 1.25 and BOUNDS["scanner-rough"]["SD"] == 0.5
