"""Amendment 9's low-contrast rows (bench/standin_profile.py) and the spread of real
photos they are matched to (tools/real_spread.py): a part blended by
`level_contrast` keeps the grey levels a whole photograph of the real photos' spread
keeps at the nominal contrast, whatever its own spread; flat parts and huge spreads
stay finite; the tool fails closed on a folder that is not there."""

from __future__ import annotations

import importlib.util
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
