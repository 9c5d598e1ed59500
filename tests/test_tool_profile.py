"""Tool measurement from images (issue 6): synthetic silhouettes with a known profile.

The silhouettes are drawn here, independently of the code under test: exact area coverage of
every edge pixel by 8×8 supersampling of the true contour, an optical blur, vignetting, sensor
noise and 8-bit quantisation. The expected numbers are the profile the images were drawn with.
"""
import json

import cv2
import numpy as np
import pandas as pd
import pytest

from stages import InputError
from stages import tool_measure as tm
from stages.tool_measure import tool_profile_command

UM_PER_PX = 1.0
D_MM = 1.0                       # Ø1 mm ball (seed 003's tool) at 1 µm/px: R = 500 px
R_PX = 500.0
H, W, XC, ZC = 680, 1120, 560.0, 100.0
ECC_UM, ECC_PHASE = 5.0, 20.0
ANGLES = np.arange(6) * 60.0
GRID = np.round(np.arange(901) * 0.1, 1)
BAND = (GRID >= 5) & (GRID <= 85)


def dent_um(q):
    """Known contour error: a 3 µm dent at 45° (positive = tool smaller)."""
    return 3.0 * np.exp(-0.5 * ((np.asarray(q) - 45.0) / 4.0) ** 2)


def wear_um(q):
    """Known wear land of the job: 2.5 µm centred at 60°, plus 1 µm rounding of the tip."""
    q = np.asarray(q)
    return 2.5 * np.exp(-0.5 * ((q - 60.0) / 6.0) ** 2) + 1.0 * np.exp(-0.5 * (q / 12.0) ** 2)


# --------------------------------------------------------------------------------------------
# independent renderer
# --------------------------------------------------------------------------------------------

def _distance(x, y, xc, zc, r0, rho):
    """Approximate signed distance (px, < 0 inside) to a tool contour: shank above the centre
    row, flat bottom of half-width r0, corner arc of radius rho(q) around (xc ± r0, zc)."""
    dxa = np.abs(x - xc) - r0
    dy = y - zc
    d = np.empty(np.broadcast(x, y).shape)
    upper, flat = dy <= 0, (dy > 0) & (dxa <= 0)
    arc = ~upper & ~flat
    d[upper] = dxa[upper] - rho(np.full(int(upper.sum()), 90.0))
    d[flat] = dy[flat] - rho(np.zeros(int(flat.sum())))
    d[arc] = np.hypot(dxa[arc], dy[arc]) - rho(np.degrees(np.arctan2(dxa[arc], dy[arc])))
    return d


def render(rho, xc=XC, zc=ZC, r0=0.0, h=H, w=W, seed=0, bright=205.0, dark=28.0, noise=2.5, blur=0.8):
    """8-bit backlit silhouette: tool dark, axis vertical, tip down."""
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    d = _distance(xx, yy, xc, zc, r0, rho)
    cover = (d < 0).astype(float)
    ey, ex = np.nonzero(np.abs(d) < 1.5)
    o = (np.arange(8) + 0.5) / 8 - 0.5
    oy, ox = np.meshgrid(o, o, indexing="ij")
    cover[ey, ex] = (_distance(ex[:, None] + ox.ravel(), ey[:, None] + oy.ravel(), xc, zc, r0, rho) < 0).mean(1)
    cover = cv2.GaussianBlur(cover, (0, 0), blur)
    vignette = 1.0 - 0.3 * (((xx - w / 2) / w) ** 2 + ((yy - h / 2) / h) ** 2)
    img = dark + (bright * vignette - dark) * (1.0 - cover)
    img += np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def tool_images(error_fn, zc=ZC, seed=0):
    """One image per spindle angle; the tool axis swings by the eccentricity."""
    return [render(lambda q: R_PX - error_fn(q) / UM_PER_PX,
                   xc=XC + ECC_UM / UM_PER_PX * np.cos(np.radians(a - ECC_PHASE)), zc=zc, seed=seed + k)
            for k, a in enumerate(ANGLES)]


def measure(images, **kw):
    ms = [tm.measure_image(im, 255.0, UM_PER_PX, D_MM, "ball", **kw) for im in images]
    return tm.measure_tool(ms, ANGLES, UM_PER_PX)


@pytest.fixture(scope="module")
def dented():
    return measure(tool_images(dent_um))


def rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


# --------------------------------------------------------------------------------------------
# profile, eccentricity, envelope, wear
# --------------------------------------------------------------------------------------------

def test_dent_recovered_with_eccentricity(dented):
    profile, summary = dented
    assert list(profile.columns) == ["contact_deg", "error_um", "error_raw_um"]
    np.testing.assert_allclose(profile["contact_deg"], GRID)
    e_filtered = rms(profile["error_um"].to_numpy()[BAND] - dent_um(GRID[BAND]))
    e_raw = rms(profile["error_raw_um"].to_numpy()[BAND] - dent_um(GRID[BAND]))
    print(f"contour error RMS over 5-85°: filtered {e_filtered:.3f} µm, raw {e_raw:.3f} µm")
    assert e_filtered <= 0.5 and e_raw <= 0.5
    peak = profile["error_um"].to_numpy()
    assert abs(GRID[np.argmax(peak)] - 45.0) <= 0.5 and abs(peak.max() - 3.0) <= 0.3
    ecc = summary["eccentricity"]
    print(f"eccentricity {ecc['eccentricity_um']:.3f} µm (true {ECC_UM}), phase {ecc['phase_deg']:.1f}°")
    assert abs(ecc["eccentricity_um"] - ECC_UM) <= 1.0
    assert abs((ecc["phase_deg"] - ECC_PHASE + 180) % 360 - 180) <= 5.0
    offsets = [im["axis_offset_um"] for im in summary["images"]]
    np.testing.assert_allclose(offsets, ECC_UM * np.cos(np.radians(ANGLES - ECC_PHASE)), atol=0.3)


def test_envelope_is_contour_plus_runout(dented):
    """The rotating eccentric tool sweeps a circle moved by e: support function R + e·sin q."""
    _, summary = dented
    env = np.array(summary["envelope"]["error_um"])
    expected = dent_um(GRID) - ECC_UM * np.sin(np.radians(GRID))
    print(f"envelope RMS error over 5-85°: {rms(env[BAND] - expected[BAND]):.3f} µm")
    assert rms(env[BAND] - expected[BAND]) <= 0.5


def test_wear_difference_in_a_common_frame(dented):
    """After the job: wear land + tip rounding, tool re-positioned 0.3 µm lower in the frame."""
    before, summary = dented
    after, _ = measure(tool_images(lambda q: dent_um(q) + wear_um(q), zc=ZC + 0.3, seed=50),
                       centre_z_px=summary["centre_z_px"])
    w = tm.wear_profile(before, after, cut_length_m=120.0)
    err = w["wear_um"].to_numpy() - wear_um(GRID)
    print(f"wear error over 5-85°: max {np.abs(err[BAND]).max():.3f} µm, RMS {rms(err[BAND]):.3f} µm")
    assert np.abs(err[BAND]).max() <= 0.7
    np.testing.assert_allclose(w["wear_rate_um_per_m"], w["wear_um"] / 120.0)
    assert (w["cut_length_m"] == 120.0).all()


def test_bull_nose_corner_profile():
    """Bull-nose Ø1 mm, corner radius 0.2 mm, 2 µm dent at 60° of the corner arc."""
    rc, r0 = 200.0, 300.0
    err_fn = lambda q: 2.0 * np.exp(-0.5 * ((np.asarray(q) - 60.0) / 5.0) ** 2)
    img = render(lambda q: rc - err_fn(q), zc=150.0, r0=r0, h=500)
    m = tm.measure_image(img, 255.0, UM_PER_PX, D_MM, "bull", corner_radius_mm=0.2)
    e = m["error_um"].mean(axis=0)
    assert rms(e[BAND] - err_fn(GRID[BAND])) <= 0.3
    assert abs(m["diameter_um"] - 1000.0) <= 0.5


def test_lowpass_is_the_iso_gaussian():
    """ISO 16610-21: a sinusoid at the cutoff wavelength keeps 50 % of its amplitude."""
    q = GRID
    for wavelength, gain in [(5.0, 0.5), (50.0, 0.5 ** ((5.0 / 50.0) ** 2))]:
        y = np.sin(2 * np.pi * q / wavelength)
        f = tm.lowpass(y, cutoff_deg=5.0)
        mid = (q > 20) & (q < 70)
        assert abs(np.abs(f[mid]).max() - gain) < 0.01


def test_eccentricity_closed_form():
    th = np.array([0.0, 45.0, 90.0, 200.0, 300.0])
    x = 12.0 + 7.0 * np.cos(np.radians(th - 33.0))
    e = tm.eccentricity(x, th)
    assert abs(e["eccentricity_um"] - 7.0) < 1e-9 and abs(e["phase_deg"] - 33.0) < 1e-6
    assert e["spindle_axis_um"] == pytest.approx(12.0)
    assert tm.eccentricity([1.0], [0.0])["eccentricity_um"] is None
    assert tm.eccentricity([0.0, 4.0], [0.0, 180.0])["lower_bound"]


def test_cut_length_from_passes():
    passes = pd.DataFrame({"pass_id": [0, 1, 2, 3], "motion": [0, 1, 1, 2],
                           "x0_mm": [0, 0, 3, 3], "y0_mm": [0, 0, 4, 4], "z0_mm": [50, 0, 0, 0],
                           "x1_mm": [0, 3, 3, 3], "y1_mm": [0, 4, 4, 4], "z1_mm": [0, 0, 0, 2]})
    assert tm.cut_length_m(passes) == pytest.approx((5.0 + 0.0 + 2.0) / 1000)
    cf = pd.DataFrame({"pass_id": [1, 2, 3], "is_cutting": [True, True, False]})
    assert tm.cut_length_m(passes, cf) == pytest.approx(5.0 / 1000)


# --------------------------------------------------------------------------------------------
# the command: outputs, and bad images
# --------------------------------------------------------------------------------------------

def _write_set(d, images):
    d.mkdir(parents=True, exist_ok=True)
    for a, im in zip(ANGLES, images):
        cv2.imwrite(str(d / f"t1_{int(a):03d}deg.png"), im)
    return d


def test_command_writes_csv_json_png(tmp_path):
    d = _write_set(tmp_path / "imgs", tool_images(dent_um, seed=100))
    out = tmp_path / "out" / "t1_profile.csv"
    res = tool_profile_command(d, UM_PER_PX, D_MM, "ball", out)
    df = pd.read_csv(out)
    assert list(df.columns) == ["contact_deg", "error_um", "error_raw_um"] and len(df) == 901
    assert rms(df["error_um"].to_numpy()[BAND] - dent_um(GRID[BAND])) <= 0.5
    js = json.loads(out.with_suffix(".json").read_text())
    assert js["n_images"] == 6 and js["spindle_angles_from"] == "file names"
    assert abs(js["eccentricity_um"] - ECC_UM) <= 1.0
    assert len(js["envelope"]["error_um"]) == 901 and len(js["images"]) == 6
    assert {"axis_offset_um", "spindle_deg", "file"} <= set(js["images"][0])
    assert js["fit"]["reference"] == "lsq"
    png = cv2.imread(str(out.with_suffix(".png")))
    assert png is not None and png.shape[1] > 1000
    assert res["csv"] == str(out) and sorted(p.name for p in out.parent.iterdir()) == [
        "t1_profile.csv", "t1_profile.json", "t1_profile.png"]


def _good_image():
    return render(lambda q: R_PX + 0 * q, seed=7)


def _bad(kind, path):
    """Write a bad image of the given kind at path; return (um_per_px, expected words)."""
    rng = np.random.default_rng(3)
    if kind == "unreadable":
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + rng.bytes(500))
        return UM_PER_PX, "unreadable"
    if kind == "empty":
        path.write_bytes(b"")
        return UM_PER_PX, "empty"
    if kind == "blank":
        cv2.imwrite(str(path), np.full((H, W), 200, np.uint8))
        return UM_PER_PX, "empty"
    if kind == "saturated":
        cv2.imwrite(str(path), np.clip(_good_image().astype(float) * 1.6, 0, 255).astype(np.uint8))
        return UM_PER_PX, "saturated"
    if kind == "wrong scale":
        cv2.imwrite(str(path), _good_image())
        return 1.25, "wrong scale"            # the images are at 1 µm/px
    if kind == "no tool":
        cv2.imwrite(str(path), np.clip(200 + rng.normal(0, 2.5, (H, W)), 0, 255).astype(np.uint8))
        return UM_PER_PX, "no tool"
    raise ValueError(kind)


@pytest.mark.parametrize("kind", ["unreadable", "empty", "blank", "saturated", "wrong scale", "no tool"])
def test_bad_image_names_the_file_and_writes_nothing(tmp_path, kind):
    d = tmp_path / "imgs"
    d.mkdir()
    good = _good_image()
    cv2.imwrite(str(d / "t1_000deg.png"), good)
    cv2.imwrite(str(d / "t1_120deg.png"), good)
    bad = d / "t1_240deg.png"
    um, words = _bad(kind, bad)
    out = tmp_path / "out" / "p.csv"
    with pytest.raises(InputError) as exc:
        tool_profile_command(d, um, D_MM, "ball", out)
    msg = str(exc.value)
    print(kind, "→", msg)
    assert words in msg
    if kind != "wrong scale":                 # a wrong scale is wrong for every file: the first is named
        assert str(bad) in msg
    else:
        assert str(d / "t1_000deg.png") in msg
    assert not out.parent.exists() or not any(out.parent.iterdir())


def test_tool_not_in_field_and_no_images(tmp_path):
    d = tmp_path / "imgs"
    d.mkdir()
    with pytest.raises(InputError, match="no images"):
        tool_profile_command(d, UM_PER_PX, D_MM, "ball", tmp_path / "p.csv")
    cut = _good_image()[:560]                  # tip cropped off
    cv2.imwrite(str(d / "a.png"), cut)
    with pytest.raises(InputError, match=r"a\.png: the tool reaches the bottom edge"):
        tool_profile_command(d, UM_PER_PX, D_MM, "ball", tmp_path / "p.csv")


# --------------------------------------------------------------------------------------------
# composite compensation (seed 002)
# --------------------------------------------------------------------------------------------

def test_contact_angle_is_arccos_nz():
    q = np.radians([0.0, 30.0, 45.0, 90.0])
    n = np.column_stack([np.sin(q) * np.cos(1.0), np.sin(q) * np.sin(1.0), np.cos(q)]) * 3.0
    np.testing.assert_allclose(tm.contact_angle_deg(n), [0.0, 30.0, 45.0, 90.0], atol=1e-9)


def _part_points(rng, left_fn):
    """Floor (q = 0), 45° chamfer face, wall (q = 90) joined by fillets (q continuous),
    the measured deviation (µm, + = material left) given as a function of q, 0.1 µm noise."""
    q = np.concatenate([np.zeros(200), rng.uniform(0, 45, 400), np.full(300, 45.0),
                        rng.uniform(45, 90, 400), np.full(200, 90.0)])
    az = rng.uniform(0, 2 * np.pi, q.size)
    qr = np.radians(q)
    normals = np.column_stack([np.sin(qr) * np.cos(az), np.sin(qr) * np.sin(az), np.cos(qr)])
    points = rng.uniform(-20, 20, (q.size, 3))
    return points, left_fn(q) + rng.normal(0, 0.1, q.size), normals


def _plateau(q, centre, height, flat=2.0, taper=3.0):
    """height within ±flat of centre, cosine taper to 0 over the next `taper` degrees."""
    a = np.abs(np.asarray(q) - centre)
    t = np.clip((a - flat) / taper, 0, 1)
    return height * 0.5 * (1 + np.cos(np.pi * t))


def test_seed_002_example_two_um_left_at_45_becomes_a_dent():
    """Seed 002 Fig. 10-12: 2 µm left on the 45° surface → a 2 µm dent at 45° of the composite
    profile between transition points found from the data; an overcut at 70° gives a bump."""
    rng = np.random.default_rng(2)
    first = pd.DataFrame({"contact_deg": GRID, "error_um": 0.5 * np.sin(np.radians(4 * GRID))})
    left = lambda q: _plateau(q, 45.0, 2.0) + _plateau(q, 70.0, -1.0, flat=1.0)
    pts, dev, nrm = _part_points(rng, left)
    out = tm.composite_profile(first, pts, dev, nrm)
    added = (out["error_um"] - out["first_um"]).to_numpy()
    i45 = int(np.flatnonzero(GRID == 45.0)[0])
    print("composite - first at 45°:", added[i45], "transitions:", out.attrs["transitions"])
    assert added[i45] == pytest.approx(2.0, abs=0.1)
    (r1, r2) = out.attrs["transitions"]
    assert 38.0 <= r1["x1_deg"] <= 43.0 and 47.0 <= r1["x2_deg"] <= 52.0 and r1["peak_um"] > 0
    assert 63.0 <= r2["x1_deg"] <= 69.0 and 71.0 <= r2["x2_deg"] <= 77.0 and r2["peak_um"] < 0
    i70 = int(np.flatnonzero(GRID == 70.0)[0])
    assert added[i70] == pytest.approx(-1.0, abs=0.15)
    outside = ~out["in_transition"].to_numpy()
    assert np.all(added[outside] == 0.0)
    assert outside[GRID < 35].all() and outside[(GRID > 55) & (GRID < 60)].all() and outside[GRID > 80].all()


def test_composite_when_part_was_cut_uncompensated():
    """Part cut without the first-error correction shows first + second; the composite is the same."""
    rng = np.random.default_rng(4)
    first_fn = lambda q: 1.5 * np.exp(-0.5 * ((np.asarray(q) - 30) / 5) ** 2)
    first = pd.DataFrame({"contact_deg": GRID, "error_um": first_fn(GRID)})
    pts, dev, nrm = _part_points(rng, lambda q: first_fn(q) + _plateau(q, 45.0, 2.0))
    out = tm.composite_profile(first, pts, dev, nrm, first_applied=False)
    added = (out["error_um"] - out["first_um"]).to_numpy()
    assert added[GRID == 45.0][0] == pytest.approx(2.0, abs=0.1)
    assert len(out.attrs["transitions"]) == 1            # the tool's own 30° dent is not counted twice
    down = np.array([[0.0, 0.0, 0.0]])
    with pytest.raises(InputError, match="zero normal"):
        tm.composite_profile(first, down, [1.0], down)


def _cut_bowl(tool_error_um, offset_um, t_deg, R=3.0, Rw=10.0):
    """2-D closed-loop check, independent of the pipeline: a ball (radius R - tool_error(q))
    finishes a concave bowl of radius Rw; each tool position sits on the nominal offset path
    moved by offset_um(q) along the normal (+ = away from the material). Returns the machined
    deviation along the normal (µm, + = material left) at bowl angles t_deg, as the first point
    along the normal ray that any tool position removes (brute force over neighbours)."""
    tp_deg = np.arange(-3.0, 91.0, 0.02)
    t = np.radians(tp_deg)
    n_tool = np.column_stack([-np.sin(t), np.cos(t)])
    p_tool = np.column_stack([Rw * np.sin(t), Rw - Rw * np.cos(t)])
    centres = p_tool + (R + 1e-3 * offset_um(tp_deg))[:, None] * n_tool
    tj = np.radians(np.asarray(t_deg))
    p = np.column_stack([Rw * np.sin(tj), Rw - Rw * np.cos(tj)])
    n = np.column_stack([-np.sin(tj), np.cos(tj)])
    win = np.arange(-150, 151)                          # ±3° of tool positions
    i0 = np.searchsorted(tp_deg, np.asarray(t_deg))
    idx = np.clip(i0[:, None] + win[None, :], 0, tp_deg.size - 1)
    d = p[:, None, :] - centres[idx]                    # (points, window, 2)
    dn = np.einsum("pwk,pk->pw", d, n)
    rho = np.full(dn.shape, R)
    for _ in range(4):                                  # radius at the entry direction (fixed point)
        disc = dn ** 2 - np.einsum("pwk,pwk->pw", d, d) + rho ** 2
        s = -dn - np.sqrt(np.maximum(disc, 0))
        v = d + s[..., None] * n[:, None, :]            # centre → entry point
        q = np.degrees(np.arctan2(np.abs(v[..., 0]), -v[..., 1]))
        rho = R - 1e-3 * tool_error_um(q)
    s = np.where(disc > 0, s, np.inf)
    return 1e3 * s.min(axis=1)


def test_composite_closed_loop_removes_the_left_material():
    """Tool with a measured dent; an unmodelled effect (e.g. deflection) lifts the tool 2 µm off
    the 45° surface. Cut 1 with the first error compensated leaves 2 µm there; the composite
    profile built from cut 1's measurement removes it in cut 2."""
    tool_err = lambda q: dent_um(q)
    lift = lambda q: _plateau(q, 45.0, 2.0)
    first = pd.DataFrame({"contact_deg": GRID, "error_um": dent_um(GRID)})
    t_meas = np.arange(2.0, 86.0, 0.1)
    cut1 = _cut_bowl(tool_err, lambda q: lift(q) - np.interp(q, GRID, first["error_um"]), t_meas)
    at45 = np.abs(t_meas - 45.0) < 1e-6
    assert cut1[at45][0] == pytest.approx(2.0, abs=0.1)
    tj = np.radians(t_meas)
    normals = np.column_stack([-np.sin(tj), np.zeros_like(tj), np.cos(tj)])
    points = np.column_stack([10 * np.sin(tj), np.zeros_like(tj), 10 - 10 * np.cos(tj)])
    comp = tm.composite_profile(first, points, cut1, normals)
    cut2 = _cut_bowl(tool_err, lambda q: lift(q) - np.interp(q, GRID, comp["error_um"]), t_meas)
    print(f"closed loop: left at 45° {cut1[at45][0]:.3f} → {cut2[at45][0]:.3f} µm; "
          f"max |err| {np.abs(cut1).max():.3f} → {np.abs(cut2).max():.3f} µm")
    assert abs(cut2[at45][0]) <= 0.1
    assert np.abs(cut2).max() <= 0.3 < np.abs(cut1).max()


def test_16bit_colour_images_and_angles_from_name_order(tmp_path):
    """16-bit and colour files load as grey; without angles in the names the images are taken
    as evenly spaced over a turn (here 0, 120, 240° as rendered)."""
    d = tmp_path / "imgs"
    d.mkdir()
    for k, a in enumerate([0.0, 120.0, 240.0]):
        im = render(lambda q: R_PX - dent_um(q), xc=XC + 5.0 * np.cos(np.radians(a)), seed=200 + k)
        if k == 0:
            im = (im.astype(np.uint16) * 257)
        elif k == 1:
            im = cv2.cvtColor(im, cv2.COLOR_GRAY2BGR)
        cv2.imwrite(str(d / f"img{k}.png"), im)
    paths = tm.list_images(d)
    angles, source = tm.spindle_angles(paths)
    np.testing.assert_allclose(angles, [0.0, 120.0, 240.0])
    assert source == "assumed evenly spaced"
    assert tm.load_image(paths[0])[1] == 65535.0
    res = tool_profile_command(d, UM_PER_PX, D_MM, "ball", tmp_path / "p.csv")
    assert abs(res["eccentricity_um"] - 5.0) <= 1.0
    assert abs((res["eccentricity"]["phase_deg"] + 180) % 360 - 180) <= 5.0
    mixed = d / "t1_090deg.png"
    cv2.imwrite(str(mixed), render(lambda q: R_PX + 0 * q))
    with pytest.raises(InputError, match="img0.png: no spindle angle"):
        tm.spindle_angles(tm.list_images(d))


@pytest.mark.parametrize("n, noise", [(60, 1.0), (300, 0.5), (3000, 0.3)])
def test_composite_adds_nothing_for_pure_noise(n, noise):
    """Measurements with no systematic error (noise only, sparse to dense): no transition
    region, the composite is the first error unchanged."""
    first = pd.DataFrame({"contact_deg": GRID, "error_um": dent_um(GRID)})
    for seed in range(5):
        rng = np.random.default_rng(seed)
        q = np.radians(rng.uniform(0, 90, n))
        normals = np.column_stack([np.sin(q), np.zeros(n), np.cos(q)])
        out = tm.composite_profile(first, np.zeros((n, 3)), rng.normal(0, noise, n), normals)
        assert out.attrs["transitions"] == []
        np.testing.assert_array_equal(out["error_um"], out["first_um"])
