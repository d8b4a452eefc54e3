"""The profile's low-contrast rows (bench/standin_profile.py) and the spread of real
photos they are matched to (tools/real_spread.py): a part blended by
`level_contrast` keeps the grey levels a whole photograph of the real photos' spread
keeps at the nominal contrast, whatever its own spread; flat parts and huge spreads
stay finite; the tool fails closed on a folder that is not there."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str, path: Path):
    sys.path.insert(0, str(ROOT / "bench"))
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def profile():
    return _load("bench_standin_profile_levels", ROOT / "bench" / "standin_profile.py")


@pytest.fixture(scope="module")
def spread_tool():
    return _load("tools_real_spread", ROOT / "tools" / "real_spread.py")


def _ramp_photo(lo: float, hi: float, side: int = 200) -> np.ndarray:
    """A grey uint8 RGB photo whose luminance runs evenly from lo to hi."""
    y = np.linspace(lo, hi, side * side).reshape(side, side)
    g = np.round(y * 255.0).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=2)


def _levels(image: np.ndarray, mask: np.ndarray) -> int:
    """Distinct 8-bit luminance values between the part's 5th and 95th percentile."""
    y = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)[mask].astype(np.float64)
    lo, hi = np.percentile(y, [5, 95])
    return len(np.unique(y[(y >= lo) & (y <= hi)]))


def test_level_contrast_formula(profile):
    real = profile.REAL_SPREAD
    assert profile.level_contrast(0.05, real) == pytest.approx(0.05)
    assert profile.level_contrast(0.05, real / 2) == pytest.approx(0.10)
    assert profile.level_contrast(0.03, real / 4) == pytest.approx(0.12)
    assert profile.level_contrast(0.05, 0.0) == 1.0  # a flat part is left alone
    assert profile.level_contrast(0.05, 1e-9) == 1.0  # capped, never above 1
    assert profile.level_contrast(0.05, 1e9) == pytest.approx(0.05 * real / 1e9)


def test_luminance_spread(profile):
    photo = _ramp_photo(0.2, 0.8)
    mask = np.ones(photo.shape[:2], bool)
    assert profile.luminance_spread(photo, mask) == pytest.approx(0.54, abs=0.01)
    flat = np.full_like(photo, 128)
    assert profile.luminance_spread(flat, mask) == 0.0
    assert profile.luminance_spread(photo, np.zeros_like(mask)) == 0.0


@pytest.mark.parametrize("c0", [0.05, 0.03])
def test_every_part_keeps_a_whole_photos_levels(profile, c0):
    """A whole photo of the real spread at c0 and parts of a quarter, half and full
    that spread, each blended by its level contrast: the same grey levels (±1), and
    the plain blend leaves the faint part far fewer."""
    mask = np.ones((200, 200), bool)
    # a ramp's 5-95 % range is 0.9 of its width: this photo's spread is REAL_SPREAD
    whole = _levels(profile._contrast(_ramp_photo(0.2, 0.8), c0), mask)
    steps = c0 * profile.REAL_SPREAD * 255  # grey steps across the range
    assert steps <= whole <= steps + 2  # values = steps + 1, and 8-bit rounding
    for width in (0.15, 0.3, 0.6):
        part = _ramp_photo(0.5 - width / 2, 0.5 + width / 2)
        c = profile.level_contrast(c0, profile.luminance_spread(part, mask))
        assert abs(_levels(profile._contrast(part, c), mask) - whole) <= 1
    faint = _ramp_photo(0.5 - 0.15 / 2, 0.5 + 0.15 / 2)
    assert _levels(profile._contrast(faint, c0), mask) <= whole / 3 + 1


def test_real_spread_tool(spread_tool, tmp_path, capsys):
    assert spread_tool.main([str(tmp_path / "missing")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert spread_tool.main([str(tmp_path)]) == 2  # a folder without photos
    assert "no photo" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("not a photo")
    (tmp_path / "broken.jpg").write_bytes(b"\xff\xd8 not a jpeg")  # skipped, not fatal
    cv2.imwrite(str(tmp_path / "ramp.png"), _ramp_photo(0.1, 0.9, side=300))
    assert spread_tool.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("1 photos: whole-photo spread median 0.7")  # 0.8 x 0.9


def _square_crop(amplitude: float, ring: bool) -> np.ndarray:
    """A 224-px crop: a textured square part on black; with `ring`, its outer
    3 px darkened as a resize against black darkens them."""
    rng = np.random.default_rng(3)
    crop = np.zeros((224, 224, 3), np.float32)
    tex = 0.5 + amplitude * (rng.random((144, 144)) - 0.5)
    crop[40:184, 40:184] = tex[..., None]
    if ring:
        crop[40:184, 40:46] *= 0.3
        crop[40:184, 178:184] *= 0.3
        crop[40:46, 40:184] *= 0.3
        crop[178:184, 40:184] *= 0.3
    return crop


def test_rim_reads_inside_the_ring():
    """rim 0 is the plain statistics bit for bit; with rim 3 (version 5's) the
    luminance's level and spread are the interior's, whatever the dark ring does."""
    from ptovs.encoders import standin_stats as st

    crops = np.stack([_square_crop(0.05, False), _square_crop(0.05, True)])
    base = st.raw_features(crops)
    assert np.array_equal(base, st.raw_features(crops, {**st.PARAMS, "rim": 0}))
    rim = st.raw_features(crops, {**st.PARAMS, "rim": 3})
    lum = slice(10, 12)  # the "lum" group: mean and spread of the luminance
    assert base[1, 11] > 3 * base[0, 11]  # the ring dominates the spread ...
    assert rim[1, lum] == pytest.approx(rim[0, lum], rel=0.1)  # ... not inside it
    assert np.isfinite(rim).all()


def _profile_rows(rng, n_views: int, n_parts: int, p_clean: float, p_row: float):
    """Fake profile results: per seed, rows of [view, part, truth, prediction]."""
    out = []
    for seed in (300, 301):
        rows = {"clean": [], "daylight": [], "daylight-b": []}
        for v in range(n_views):
            for k in range(n_parts):
                for name, p in (
                    ("clean", p_clean), ("daylight", p_row), ("daylight-b", p_row)
                ):  # fmt: skip
                    rows[name].append([v, k, k, k if rng.random() < p else -1])
        out.append({"seed": seed, "rows": rows})
    return out


def test_view_interval_resamples_views(profile):
    """The appearance rows' interval resamples (seed, view) clusters: it holds the
    point, is exact where nothing varies, and narrows with more views."""
    rng = np.random.default_rng(0)
    same = _profile_rows(rng, 12, 4, 1.0, 1.0)
    assert profile.view_interval(same, ("daylight",)) == [0.0, 0.0]
    none = _profile_rows(rng, 12, 4, 1.0, 0.0)
    assert profile.view_interval(none, ("daylight",)) == [-1.0, -1.0]
    few = _profile_rows(rng, 8, 4, 0.8, 0.8)
    many = _profile_rows(rng, 200, 4, 0.8, 0.8)
    s = profile.summarise(many)
    lo, hi = s["rows"]["daylight"]["relative_ci_views"]
    assert lo <= s["rows"]["daylight"]["relative"] <= hi
    assert -0.1 < lo < 0.0 < hi < 0.1
    f_lo, f_hi = profile.view_interval(few, ("daylight",))
    assert f_hi - f_lo > hi - lo
    assert "relative_ci_views" not in s["rows"]["clean"]
    both = s["daylight_both"]  # the two draws pooled: their mean, a narrower interval
    a, b = (s["rows"][n]["relative"] for n in ("daylight", "daylight-b"))
    assert both["relative"] == pytest.approx((a + b) / 2)
    assert np.diff(both["relative_ci_views"])[0] < hi - lo
    assert np.isnan(profile.view_interval([], ("daylight",))).all()  # nothing to read


def test_summarise_rereads_a_saved_profile(profile, tmp_path, capsys):
    """--summarise prints a saved profile's rows with their intervals and measures
    nothing; anything else fails naming the file."""
    results = _profile_rows(np.random.default_rng(1), 30, 3, 0.8, 0.7)
    saved = tmp_path / "profile.json"
    saved.write_text(json.dumps({"summary": {"version": 5}, "seeds": results}))
    profile.main(["--summarise", str(saved)])
    out = capsys.readouterr().out
    assert out.startswith("version 5  clean accuracy")
    assert "daylight, both draws" in out and "daylight-b" in out
    bad = tmp_path / "other.json"
    bad.write_text('{"rows": []}')
    for path in (bad, tmp_path / "missing.json"):
        with pytest.raises(SystemExit):
            profile.main(["--summarise", str(path)])
        assert f"--summarise {path}: not a saved profile" in capsys.readouterr().err
