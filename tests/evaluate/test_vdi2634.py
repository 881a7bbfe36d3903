"""VDI/VDE 2634-2 figures on exact synthetic points: a perfect artefact gives zero, known noise the
predicted range, and the 0.3 % leave-out rule is honoured exactly."""

import math

import numpy as np
import pytest
from scipy.stats import norm

from ptpcore.evaluate.vdi2634 import (AcceptanceReport, Artefact, fit_plane, fit_sphere, left_out_count, parse_mpe,
                                      point_distance_errors, pose_figures, split_ball_bar)

RNG = np.random.default_rng(7)


def _sphere_points(centre, radius, n, rng, cap_deg=180.0):
    """``n`` points uniformly over the sphere's cap within ``cap_deg`` of its -Z pole (toward a scanner)."""
    cos_max = math.cos(math.radians(cap_deg))
    cz = rng.uniform(cos_max, 1.0, n)  # uniform in cos: uniform over the cap's area
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - cz ** 2)
    u = np.column_stack([s * np.cos(phi), s * np.sin(phi), -cz])
    return np.asarray(centre) + radius * u, u


def _plane_points(point, normal, n, rng, size=80.0):
    n_ = np.asarray(normal, float) / np.linalg.norm(normal)
    e1 = np.cross(n_, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n_, e1)
    a, b = rng.uniform(-size / 2, size / 2, (2, n))
    return np.asarray(point) + a[:, None] * e1 + b[:, None] * e2, n_


def test_a_perfect_sphere_gives_zero_form_and_size_error():
    p, _ = _sphere_points((10.0, -5.0, 30.0), 12.5, 3000, RNG, cap_deg=70)
    f = pose_figures(p, Artefact("sphere", 25.0), pose="s", method="m")
    assert abs(f.figures["PF"]) < 1e-9 and abs(f.figures["PS"]) < 1e-9
    assert f.n_left_out == left_out_count(3000) == 9
    assert np.allclose(f.fit["centre_mm"], (10.0, -5.0, 30.0), atol=1e-9)


def test_a_perfect_plane_and_ball_bar_give_zero():
    p, _ = _plane_points((50, 40, 20), (0.3, -0.1, -1.0), 2000, RNG)
    assert pose_figures(p, Artefact("plane")).figures["F"] < 1e-9
    c1, c2 = np.array([20.0, 30.0, 15.0]), np.array([85.0, 60.0, 30.0])
    pa, _ = _sphere_points(c1, 9.0, 1500, RNG, cap_deg=75)
    pb, _ = _sphere_points(c2, 9.0, 1200, RNG, cap_deg=75)
    pts = np.concatenate([pa, pb])[RNG.permutation(2700)]
    f = pose_figures(pts, Artefact("ballbar", 18.0, float(np.linalg.norm(c2 - c1))))
    assert abs(f.figures["SD"]) < 1e-9
    assert sorted(f.fit["points_per_ball"]) == [1200, 1500]


def _kept_range_prediction(n, sigma, fraction):
    """Range of ``n`` N(0, sigma) residuals after leaving out the ``floor(fraction n)`` largest |r|: each
    end sits near the two-sided ``fraction`` quantile; the sample quantile's sd is
    ``sqrt(p (1 - p) / n) / pdf(z)`` per end (p = fraction / 2), the two ends independent."""
    p = left_out_count(n, fraction) / n / 2
    z = norm.isf(p)
    sd_end = math.sqrt(p * (1 - p) / n) / norm.pdf(z)
    return 2 * z * sigma, math.sqrt(2) * sd_end * sigma


def test_known_noise_gives_the_predicted_form_range_and_an_unbiased_size():
    n, sigma, r = 40000, 0.004, 12.5
    p, u = _sphere_points((0.0, 0.0, 25.0), r, n, RNG)  # the whole sphere: radius and centre decouple
    noisy = p + RNG.normal(0, sigma, n)[:, None] * u
    s = fit_sphere(noisy)
    expected, sd = _kept_range_prediction(n, sigma, 0.003)
    assert abs(s.form_range - expected) < 4 * sd, (s.form_range, expected, sd)
    assert abs(2 * s.radius - 2 * r) < 4 * 2 * s.radius_se
    # the standard error is the one the residuals predict (sigma / sqrt(n) for a whole sphere)
    assert s.radius_se == pytest.approx(sigma / math.sqrt(n), rel=0.1)


def test_known_noise_gives_the_predicted_flatness():
    n, sigma = 30000, 0.003
    p, nrm = _plane_points((0, 0, 20), (0.2, 0.1, -1), n, RNG)
    f = fit_plane(p + RNG.normal(0, sigma, n)[:, None] * nrm)
    expected, sd = _kept_range_prediction(n, sigma, 0.003)
    assert abs(f.flatness - expected) < 4 * sd, (f.flatness, expected, sd)


@pytest.mark.parametrize("extra", [0, 1])
def test_the_leave_out_limit_is_honoured(extra):
    """Gross outliers up to floor(0.3 % N) are left out and the form range is the noise's again; one
    more than that stays in and shows in PF: the rule never leaves out more."""
    n, sigma = 5000, 0.002
    p, u = _sphere_points((0, 0, 30), 10.0, n, RNG, cap_deg=80)
    noisy = p + RNG.normal(0, sigma, n)[:, None] * u
    allowed = left_out_count(n)
    bad = RNG.choice(n, allowed + extra, replace=False)
    noisy[bad] += 0.5 * u[bad]  # 0.5 mm off the surface: 250 sigma
    s = fit_sphere(noisy)
    assert s.n_left_out == allowed and int((~s.kept).sum()) == allowed
    # with no gross outlier kept, the range is bounded by the whole noise's range (< 2 x 6 sigma here)
    if extra == 0:
        assert not np.any(s.kept[bad]) and s.form_range < 12 * sigma
    else:
        assert s.form_range > 0.4


def test_no_leave_out_keeps_every_point():
    p, _ = _sphere_points((0, 0, 30), 10.0, 1000, RNG)
    s = fit_sphere(p, leave_out=0.0)
    assert s.n_left_out == 0 and s.kept.all()


def test_ball_bar_split_follows_the_bar():
    c1, c2 = np.array([0.0, 0.0, 20.0]), np.array([60.0, 0.0, 20.0])
    pa, _ = _sphere_points(c1, 9.0, 800, RNG, cap_deg=80)
    pb, _ = _sphere_points(c2, 9.0, 700, RNG, cap_deg=80)
    a, b = split_ball_bar(np.concatenate([pa, pb]))
    assert a[:800].all() and not a[800:].any() and b[800:].all()


def test_too_few_points_name_the_pose():
    with pytest.raises(ValueError, match="sphere-03 .ptp.*finite points"):
        pose_figures(np.zeros((3, 3)), Artefact("sphere", 20.0), pose="sphere-03", method="ptp")


@pytest.mark.parametrize("text, match", [("PF=0.1,PX=2", "unknown key 'PX'"), ("PF=abc", "PF value 'abc'"),
                                         ("SD=-1", "SD value '-1' must be a positive"), ("PF", "not KEY=VALUE"),
                                         ("PF=1,pf=2", "PF given twice")])
def test_bad_mpe_text_names_the_key_or_value(text, match):
    with pytest.raises(ValueError, match=match):
        parse_mpe(text)


def test_mpe_units_and_verdicts():
    mpe = parse_mpe("PF=12um, PS=0.01mm,SD=0.02")
    assert mpe == pytest.approx({"PF": 0.012, "PS": 0.01, "SD": 0.02})
    p, _ = _sphere_points((0, 0, 30), 10.0, 2000, RNG, cap_deg=70)
    good = pose_figures(p, Artefact("sphere", 20.0), pose="a", method="m")
    off = pose_figures(p * 1.001, Artefact("sphere", 20.0), pose="b", method="m")  # 0.02 mm too big a sphere
    rep = AcceptanceReport([good, off], ("m",), mpe)
    assert rep.largest("m")["PS"]["pose"] == "b"
    assert rep.largest("m")["PS"]["value_mm"] == pytest.approx(0.02, rel=1e-6)
    assert rep.verdicts("m") == {"PF": "pass", "PS": "fail", "SD": "no pose"}
    js = rep.to_json_dict()
    assert js["verdicts"]["m"]["PS"] == "fail" and len(js["poses"]) == 2


def test_3d_distance_errors_are_zero_for_exact_points_and_see_a_scale_error():
    t1, _ = _sphere_points((0, 0, 30), 10.0, 500, RNG)
    t2, _ = _plane_points((50, 0, 20), (0, 0, -1), 400, RNG)
    scaled = [1.001 * t1, 1.001 * t2]  # a 0.1 % scale error: distance errors 0.1 % of the distance
    res = point_distance_errors({"exact": [t1, t2], "scaled": scaled}, [t1, t2], n_pairs=2000)
    assert res["exact"].kinds["same_scan"][0].max_um < 1e-6
    assert res["exact"].kinds["across_scans"][0].max_um < 1e-6
    s = res["scaled"].kinds["across_scans"][1]
    filled = s.count > 0
    centres = 0.5 * (s.edges_mm[1:] + s.edges_mm[:-1])
    # mean error in each bin ~ 0.1 % of its distance (within the bin's half width)
    half = 0.5 * np.diff(s.edges_mm)
    assert np.all(np.abs(s.mean_um[filled] - 1e3 * 1e-3 * centres[filled]) <= 1e3 * 1e-3 * half[filled] + 1e-6)
