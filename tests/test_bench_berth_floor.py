"""bench/berth_floor.py's variants and flags (nothing is flown here: the bench takes minutes;
its table is bench/noisy_training.py `rows`, tested in tests/test_bench_noisy_training.py)."""

from __future__ import annotations

import argparse

import pytest

from bench.berth_floor import VARIANTS, _variants
from policy.pointmass import VehicleModel


def test_every_variant_is_a_vehicle_model_and_padded_ones_only_report_plain_gnss() -> None:
    models = {v: VehicleModel.named(spec) for v, spec in VARIANTS.items()}
    assert models["ideal"] == VehicleModel.ideal()
    assert models["realistic"] == VehicleModel.realistic()
    for v in ("padded", "padded-exact"):
        m = models[v]
        assert m.pos_sigma_m == models["realistic"].pos_sigma_m  # padded as for plain GNSS
        assert (m.lag_s, m.gust_m_s, m.max_accel_m_s2) == (0.0, 0.0, float("inf"))  # flown exactly
        assert m.drift_m <= 0.02  # at most RTK-grade


def test_variants_flag() -> None:
    assert _variants("padded, realistic") == ["padded", "realistic"]
    for bad in ("", "padded,wobbly"):
        with pytest.raises(argparse.ArgumentTypeError, match="variants must be among"):
            _variants(bad)
