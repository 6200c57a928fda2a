"""The told share belongs to the weights: their config's `filtered_told_share` says what share of
the separation flight tells them with the filter on (issue 35's fine-tune on drifting estimates
was trained told the whole separation), in numpy, in the C core built against them, and in
`covey train`'s output; weights that state none are told the legacy 1.25 / 3."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from policy.runtime import (
    LEGACY_FILTERED_TOLD_SHARE,
    TOLD_SHARE_KEY,
    GuidancePolicy,
    config_told_share,
    filtered_told_share,
    told_separation_m,
)

SHIPPED = Path(__file__).resolve().parent.parent / "policy" / "weights" / "policy.npz"


def weights_with(tmp_path: Path, **config) -> Path:
    """The shipped weights with their config changed (None removes a key)."""
    arrays = dict(np.load(SHIPPED))
    cfg = json.loads(str(arrays["config"][()]))
    for k, v in config.items():
        if v is None:
            cfg.pop(k, None)
        else:
            cfg[k] = v
    arrays["config"] = np.array(json.dumps(cfg))
    path = tmp_path / f"w_{abs(hash(json.dumps(config, sort_keys=True)))}.npz"
    np.savez(path, **arrays)
    return path


def test_the_share_is_read_from_the_weights(tmp_path: Path) -> None:
    one = weights_with(tmp_path, **{TOLD_SHARE_KEY: 1.0})
    legacy = weights_with(tmp_path, **{TOLD_SHARE_KEY: None})
    assert filtered_told_share(one) == 1.0
    assert filtered_told_share(legacy) == LEGACY_FILTERED_TOLD_SHARE
    shipped_cfg = json.loads(str(np.load(SHIPPED)["config"][()]))
    assert filtered_told_share(None) == shipped_cfg.get(TOLD_SHARE_KEY, LEGACY_FILTERED_TOLD_SHARE)
    # flight's distance scale follows the weights; an explicit told separation still wins
    assert GuidancePolicy.load(one).dist_scale_m == pytest.approx(1.0)
    assert GuidancePolicy.load(legacy).dist_scale_m == pytest.approx(LEGACY_FILTERED_TOLD_SHARE)
    assert GuidancePolicy.load(one, policy_separation_m=2.0).dist_scale_m == pytest.approx(2 / 3)
    assert GuidancePolicy.load(one, safety_filter=False).dist_scale_m == pytest.approx(1.0)
    assert told_separation_m(6.0, True, share=0.5) == 3.0
    assert told_separation_m(6.0, False, share=0.5) == 6.0


@pytest.mark.parametrize("bad", [0.0, -1.0, 4.5, float("nan"), "1", True, None])
def test_a_bad_share_is_refused_with_the_key(tmp_path: Path, bad) -> None:
    with pytest.raises(ValueError, match=TOLD_SHARE_KEY):
        config_told_share({TOLD_SHARE_KEY: bad})
    if isinstance(bad, float) and not np.isnan(bad):
        with pytest.raises(ValueError, match=TOLD_SHARE_KEY):
            GuidancePolicy.load(weights_with(tmp_path, **{TOLD_SHARE_KEY: bad}))


def test_the_c_core_built_against_the_weights_tells_their_share(tmp_path: Path) -> None:
    """COVEY_W_FILTERED_TOLD_SHARE comes from the weights header: covey_told_separation_m (the
    PX4 module's rule) equals the runtime's for weights with and without a stated share."""
    pytest.importorskip("firmware.cpolicy")
    from firmware import export_c
    from firmware.cpolicy import CPolicy

    for share in (1.0, None):
        path = weights_with(tmp_path, **{TOLD_SHARE_KEY: share})
        want = LEGACY_FILTERED_TOLD_SHARE if share is None else share
        assert "COVEY_W_FILTERED_TOLD_SHARE" in export_c.header_text(path)
        cpol = CPolicy.load(path)
        c = cpol._lib.covey_told_separation_m(3.0, 1, 0.0)
        assert c == pytest.approx(3.0 * want, rel=1e-6)
        assert c == pytest.approx(told_separation_m(3.0, True, share=filtered_told_share(path)))


@pytest.mark.slow
def test_train_writes_the_share_it_is_given(tmp_path: Path) -> None:
    from policy.train_cli import cli

    cli(
        [
            "--episodes", "40", "--num-envs", "8", "--num-steps", "8", "--threads", "1",
            "--no-progress", "--drift-m", "0.5", "--filtered-told-share", "1.0",
            "--safety-filter", "--out", str(tmp_path / "run"),
        ]
    )  # fmt: skip
    cfg = json.loads(str(np.load(tmp_path / "run" / "final.npz")["config"][()]))
    assert cfg[TOLD_SHARE_KEY] == 1.0
    assert filtered_told_share(tmp_path / "run" / "final.npz") == 1.0
