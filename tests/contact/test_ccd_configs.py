"""The shipped 4K and 8K hairballs set a contact thickness below their closest rest pair,
so strand_contact_mode = "ccd" runs on them without rest-pose exemptions."""

from pathlib import Path

import numpy as np
import pytest

from lc_petsc.config import load_config
from lc_petsc.contact import StrandContact
from lc_petsc.elements.segment_contact import distance
from lc_petsc.scene.sources import source_from_config


@pytest.mark.parametrize("name, closest", [("hairball_4k", 0.0945), ("hairball_8k", 0.0604)])
def test_big_hairballs_are_clear_of_their_thickness(name, closest):
    cfg = load_config(Path(__file__).resolve().parents[2] / "configs" / f"{name}.toml")
    d0 = cfg.physics.strand_thickness
    n = cfg.scene.n_wisps
    b = source_from_config(cfg.scene, cfg.material, cfg.physics).load(0, n)
    seg = np.concatenate([np.arange(b.offsets[w], b.offsets[w + 1] - 1) for w in range(n)])
    wisp = np.repeat(np.arange(n), np.diff(b.offsets) - 1)
    P = np.stack([b.positions[seg], b.positions[seg + 1]], axis=1)
    # every pair of different wisps within 1.25 d0 (the broad phase is exact)
    ij = StrandContact.candidates(P, wisp, len(P), 1.25 * d0)
    d = distance(np.concatenate([P[ij[:, 0]], P[ij[:, 1]]], axis=1))
    assert len(d) > 1000                          # neighbours are searched
    assert d.min() == pytest.approx(closest, abs=5e-5)
    assert d0 < d.min()
    # the default thickness (twice the tip radius) would need exemptions: the control
    default = 2.0 * cfg.material.tip_radius * min(1.0, np.sqrt(2000.0 / n))
    assert (d < default).sum() > 100
