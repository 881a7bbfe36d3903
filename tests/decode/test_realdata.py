"""Real captures from other fringe systems (tests/data/README.md), decoded through ptp-dataset/2."""

from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.io.dataset import DatasetSource
from ptpcore.io.decodedfile import load_decoded
from ptpcore.decode.phase import REASON_KEYS
from ptpcore.rig import load_rig

DATA = Path(__file__).resolve().parents[1] / "data"


# --------------------------------------------------------------------------- OpenCSP SOFAST

SOFAST_SCREEN = 759.0  # px: their fractional screen coordinate times this is ours


def _sofast_dataset(folder: Path) -> Path:
    """A ptp-dataset/2 folder from OpenCSP's HDF5 capture: fractional periods, shift_sign = -1."""
    with h5py.File(DATA / "opencsp-sofast" / "measurement_fringes.h5", "r") as f:
        images = f["MeasurementSofastFringe/fringe_images"][()]  # (H, W, 32): y's 16 first, then x's
        cycles_x = f["MeasurementSofastFringe/fringe_periods_x"][()]
        cycles_y = f["MeasurementSofastFringe/fringe_periods_y"][()]
    h, w, _ = images.shape
    px = [float(SOFAST_SCREEN / c) for c in cycles_x]
    py = [float(SOFAST_SCREEN / c) for c in cycles_y]
    folder.mkdir(parents=True)
    rig = f'''format = "ptp-dataset/2"

[camera]
width = {w}
height = {h}
bit_depth = 8

[lcd]
width = 760
height = 760
pitch_mm = [1.0, 1.0]

[stage]
z_mm = [0.0]

[fringes]
directions = ["x", "y"]
periods_px = [{", ".join(repr(p) for p in px)}]
steps = 4
shift_sign = -1

[fringes.y]
periods_px = [{", ".join(repr(p) for p in py)}]

[images]
template = "{{dir}}_T{{period}}_n{{step}}_z{{pos}}.png"
'''
    (folder / "rig.toml").write_text(rig)
    for d, first, periods in (("y", 0, py), ("x", 16, px)):
        for j, t in enumerate(periods):
            for n in range(4):
                name = f"{d}_T{t!r}_n{n}_z0.png"
                cv2.imwrite(str(folder / name), np.ascontiguousarray(images[:, :, first + 4 * j + n]))
    return folder


def test_sofast_capture_decodes_to_opencsp_screen_points(tmp_path, capfd):
    ds = _sofast_dataset(tmp_path / "sofast")
    rig = load_rig(ds)
    assert rig.fringes.periods("x")[0] == pytest.approx(843.333, abs=1e-3)
    out = tmp_path / "sofast.decoded.h5"
    capfd.readouterr()
    assert main(["decode", str(ds), "--out", str(out), "-q"]) == 0
    dec = load_decoded(out)
    assert dec.u.shape == (1, 154, 203) and dec.reasons.shape == (1, 2, 154, 203)
    with h5py.File(DATA / "opencsp-sofast" / "expected_screen_points.h5", "r") as f:
        base = "DataSofastCalculation/facet/facet_000/"
        mask = f[base + "CalculationImageProcessingFacet/mask_processed"][()]
        frac = f[base + "CalculationDataGeometryFacet/v_screen_points_fractional_screens"][()]
    u_ref = np.full(mask.shape, np.nan)
    v_ref = np.full(mask.shape, np.nan)
    u_ref[mask] = frac[0] * SOFAST_SCREEN
    v_ref[mask] = (1.0 - frac[1]) * SOFAST_SCREEN  # their screen y points up
    u, v = dec.u[0], dec.v[0]
    ours = np.isfinite(u) & np.isfinite(v)
    both = mask & ours
    coverage = both.sum() / mask.sum()
    assert coverage >= 0.85, f"decoded {100 * coverage:.1f} % of OpenCSP's pixels"
    du, dv = u[both] - u_ref[both], v[both] - v_ref[both]
    rms = np.sqrt(np.mean(np.concatenate([du, dv]) ** 2))
    assert rms < 0.05, f"RMS {rms:.4f} screen px"
    # Every pixel we reject carries a reason, per direction.
    for di, coord in ((0, u), (1, v)):
        r = dec.reasons[0, di]
        assert np.all((r != 0) == ~np.isfinite(coord))
    assert set(dec.reason_bits) == set(REASON_KEYS.values())


def test_sofast_with_the_wrong_shift_sign_names_the_fix(tmp_path, capfd):
    ds = _sofast_dataset(tmp_path / "sofast")
    text = (ds / "rig.toml").read_text().replace("shift_sign = -1\n", "")
    (ds / "rig.toml").write_text(text)
    capfd.readouterr()
    assert main(["decode", str(ds), "--out", str(tmp_path / "x.decoded.h5"), "-q"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    # A mirrored map with another origin decodes as consistently: both are listed (issue 32), the plain sign first.
    assert len(err) == 1 and "(1) `shift_sign = -1`;" in err[0] and "cannot tell them apart" in err[0]


# --------------------------------------------------------------------------- kamino410 Gray code

K_T = (100.0, 200.0 / 3.0)  # coarse (Gray cells) and fine sinusoid periods, projector px
K_ORIGIN = -2.0 * np.pi / 3.0  # steps at -2pi/3, 0, +2pi/3
K_BITS = {"x": 5, "y": 4}


def _kamino_frames() -> dict:
    """Frame -> file, in the order the generator writes them (tests/data/README.md)."""
    frames = {}
    for di, d in enumerate("xy"):
        for j, first in ((1, 0), (0, 3)):  # period_index 1 (66.7 px) first, then 0 (100 px)
            for n in range(3):
                frames[("phase", d, j, n)] = f"pat{6 * di + first + n:02d}.png"
    first = {"x": 12, "y": 22}
    for d in "xy":
        for b in range(K_BITS[d]):
            frames[("gray", d, b, False)] = f"pat{first[d] + 2 * b:02d}.png"
            frames[("gray", d, b, True)] = f"pat{first[d] + 2 * b + 1:02d}.png"
    frames[("ref", "white")] = "pat30.png"
    frames[("ref", "black")] = "pat31.png"
    return frames


def _kamino_dataset(folder: Path) -> Path:
    folder.mkdir(parents=True)
    src = DATA / "kamino410-object1"
    h, w = cv2.imread(str(src / "pat00.png"), cv2.IMREAD_UNCHANGED).shape
    entries = []
    for key, name in _kamino_frames().items():
        (folder / name).write_bytes((src / name).read_bytes())
        if key[0] == "phase":
            entries.append(f'dir = "{key[1]}"\nperiod_index = {key[2]}\nstep = {key[3]}')
        elif key[0] == "gray":
            entries.append(f'dir = "{key[1]}"\ngray_bit = {key[2]}\ninverse = {str(key[3]).lower()}')
        else:
            entries.append(f'reference = "{key[1]}"')
        entries[-1] += f'\nfile = "{name}"\n'
    text = f'''format = "ptp-dataset/2"

[camera]
width = {w}
height = {h}

[lcd]
width = 1920
height = 1080
pitch_mm = [0.1, 0.1]

[stage]
z_mm = [0.0]

[fringes]
directions = ["x", "y"]
periods_px = [{K_T[0]!r}, {K_T[1]!r}]
steps = 3
offset = 127.5
amplitude = 127.5
phase_origin_rad = {K_ORIGIN!r}
unwrap = "gray"
gray_bits = 5
gray_inverse = true

[fringes.y]
gray_bits = 4

[images]
''' + "".join("\n[[images.frames]]\n" + e for e in entries)
    (folder / "rig.toml").write_text(text)
    return folder


def _independent_decode(folder: Path):
    """The capture decoded by hand, with no ptpcore code: 3-step phases as kamino410's decoder,
    Gray code against the inverse, then at the cell edges (within a quarter cycle of the phase
    jump) the cell whose edge bit is the weakly decided one; then the fine period."""
    frames = _kamino_frames()

    def img(key):
        return cv2.imread(str(folder / frames[key]), cv2.IMREAD_GRAYSCALE).astype(np.float64)

    out = {}
    for d in "xy":
        nb = K_BITS[d]
        wrapped = []
        for j in (0, 1):
            i1, i2, i3 = (img(("phase", d, j, n)) for n in range(3))
            wrapped.append(np.mod(np.arctan2(np.sqrt(3.0) * (i1 - i3), 2.0 * i2 - i1 - i3), 2 * np.pi))
        diffs = np.stack([img(("gray", d, b, False)) - img(("gray", d, b, True)) for b in range(nb)])
        weights = 1 << np.arange(nb - 1, -1, -1)
        gray = np.tensordot(weights, (diffs > 0).astype(np.int64), axes=(0, 0))
        # Gray -> binary by lookup: the table of every code of nb bits.
        table = np.zeros(1 << nb, np.int64)
        for cell in range(1 << nb):
            table[cell ^ (cell >> 1)] = cell
        cell = table[gray]
        # Edge bit between cells c and c + 1 (index into diffs, 0 = most significant), by table.
        edge = np.full((1 << nb) + 1, -1)
        for c in range((1 << nb) - 1):
            x = (c ^ (c >> 1)) ^ ((c + 1) ^ ((c + 1) >> 1))
            edge[c + 1] = nb - x.bit_length()  # edge[c + 1]: between c and c + 1
        strength = np.abs(diffs) / 2.0

        def edge_strength(lower_cell):
            e = edge[np.clip(lower_cell + 1, 0, 1 << nb)]
            s = np.take_along_axis(strength, np.clip(e, 0, nb - 1)[None], 0)[0]
            return np.where((e >= 0) & (lower_cell >= 0), s, np.inf)

        t = wrapped[0] / (2 * np.pi)
        below, above = edge_strength(cell - 1), edge_strength(cell)
        cell = cell + ((t < 0.25) & (above < 0.5 * below)) - ((t > 0.75) & (below < 0.5 * above))
        coarse = (cell + t) * K_T[0]
        f = wrapped[1] / (2 * np.pi)
        fine = (np.round(coarse / K_T[1] - f) + f) * K_T[1]
        # Valid where the phase is not within rounding of its jump with the code undecisive
        # (there which side of the jump the pixel is on is float rounding; no edge bit tells).
        at_jump = (np.minimum(t, 1.0 - t) < 1e-6) & ~((above < 0.5 * below) | (below < 0.5 * above))
        out[d] = np.where(at_jump, np.nan, fine)
    return out["x"], out["y"]


def test_kamino410_gray_code_capture(tmp_path, capfd):
    ds = _kamino_dataset(tmp_path / "kamino")
    out = tmp_path / "k.decoded.h5"
    capfd.readouterr()
    assert main(["decode", str(ds), "--out", str(out), "-q"]) == 0
    dec = load_decoded(out)
    u, v = dec.u[0].astype(np.float64), dec.v[0].astype(np.float64)
    white = cv2.imread(str(ds / "pat30.png"), cv2.IMREAD_GRAYSCALE).astype(float)
    black = cv2.imread(str(ds / "pat31.png"), cv2.IMREAD_GRAYSCALE).astype(float)
    lit = (white - black) > 40  # the object and the wall the projector lights
    # Both directions decoded over the lit scene.
    for name, c in (("u", u), ("v", v)):
        covered = np.isfinite(c)[lit].mean()
        assert covered > 0.8, f"{name} decoded on {100 * covered:.1f} % of the lit pixels"
    ui, vi = _independent_decode(ds)
    for name, ours, ref in (("u", u, ui), ("v", v, vi)):
        m = np.isfinite(ours) & np.isfinite(ref)
        assert m.sum() > 0.99 * np.isfinite(ours).sum()
        assert np.max(np.abs(ours[m] - ref[m])) < 0.01, name
    # No one-cycle jumps: away from mask edges, no pixel differs from the mean of its two
    # neighbours along the coding direction by more than half the finest period.
    for name, c, axis in (("u", u, 1), ("v", v, 0)):
        ok = np.isfinite(c)
        inner = cv2.erode(ok.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        prev, nxt = np.roll(c, 1, axis), np.roll(c, -1, axis)
        jump = np.abs(c - 0.5 * (prev + nxt))
        inner[[0, -1], :] = False
        inner[:, [0, -1]] = False
        bad = inner & (jump > K_T[1] / 2)
        assert bad.sum() == 0, f"{name}: {bad.sum()} one-cycle jumps"
