"""bench/male_probe.py (issue 43): the denser field it hands train-male. The probe
itself runs the stage at a landmark's size; this checks only what it builds."""

from __future__ import annotations

import pytest
import torch

from conftest import bench_module
from ptovs.field.render import WildField
from ptovs.raster import Gaussians


@pytest.fixture(scope="module")
def probe():
    yield from bench_module("male_probe")


def _field(n: int) -> WildField:
    gen = torch.Generator().manual_seed(1)
    g = Gaussians(
        means=torch.randn(n, 3, generator=gen),
        quats=torch.randn(n, 4, generator=gen),
        scales=torch.rand(n, 3, generator=gen) * 0.1 + 0.01,
        opacities=torch.rand(n, generator=gen),
    )
    return WildField(g, torch.randn(n, 16, 3, generator=gen), 3)


def test_inflate_keeps_every_gaussian_and_moves_only_the_copies(probe):
    field = _field(50)
    out = probe.inflate(field, 173)
    g, o = field.gaussians, out.gaussians
    assert len(out) == 173 and out.sh.shape == (173, 16, 3)
    # the originals come first, untouched (the loaded field is not changed either)
    assert torch.equal(o.means[:50], g.means) and torch.equal(o.scales[:50], g.scales)
    # each copy is some Gaussian's shape, opacity and colour, moved by half its
    # mean scale
    for i in range(50, 173):
        src = int(torch.nonzero((out.sh[i] == field.sh).all(-1).all(-1))[0])
        assert torch.equal(o.quats[i], g.quats[src])
        assert torch.equal(o.opacities[i], g.opacities[src])
        dist = float((o.means[i] - g.means[src]).norm())
        assert dist == pytest.approx(0.5 * float(g.scales[src].mean()), rel=1e-4)
    assert torch.isfinite(o.means).all()


def test_inflate_to_zero_or_its_own_count_is_the_field_itself(probe):
    field = _field(20)
    assert probe.inflate(field, 0) is field and probe.inflate(field, 20) is field
    # fewer than it has: the first ones (a probe below the field's count)
    assert len(probe.inflate(field, 7)) == 7


def test_patch_makes_the_loader_return_the_denser_field(probe, monkeypatch):
    from ptovs.field import render

    monkeypatch.setattr(
        render.WildField, "from_artifact", classmethod(lambda cls, art: _field(10))
    )
    probe.patch(31)
    assert len(render.WildField.from_artifact(None)) == 31
