"""``ptp diff --exact``: two LUT files identical dataset by dataset and attribute by attribute, or not."""

from __future__ import annotations

from ptpcore.cli import main
from ptpcore.simulate.virtual_rig import scaled_preset, simulate_dataset


def test_diff_exact_tells_identical_from_different(tmp_path, capsys):
    rig, sim = scaled_preset("mild", 48, None, 4)
    ds = simulate_dataset(tmp_path / "ds", rig, sim, seed=3)
    a, b, c = (tmp_path / f"{n}.lut.h5" for n in "abc")
    for out, model in ((a, "poly"), (b, "poly"), (c, "linear")):
        assert main(["calibrate", str(ds), "--out", str(out), "--model", model, "--degree", "1", "-q"]) == 0
    capsys.readouterr()
    assert main(["diff", str(a), str(b), "--exact"]) == 0  # written twice: only `created` differs
    assert capsys.readouterr().out.strip().startswith("identical:")
    assert main(["diff", str(a), str(c), "--exact"]) == 1
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) >= 2 and "difference" in out[-1]
    assert main(["diff", str(a), str(b), "--exact", "--json", str(tmp_path / "r.json")]) == 2
    assert not (tmp_path / "r.json").exists()
