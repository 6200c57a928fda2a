"""Tiny-budget trainer smoke runs, the occupancy encoder and export."""

import dataclasses
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from policy.export import cli as export_cli  # noqa: E402
from policy.model import IMPROVED, PAPER, ActorCritic, OccupancyEncoder  # noqa: E402
from policy.runtime import GuidancePolicy  # noqa: E402
from policy.train import TrainConfig, main  # noqa: E402


def test_paper_network_shapes():
    m = ActorCritic(PAPER)
    assert m.encoder.lstm.input_size == 3 and m.encoder.lstm.hidden_size == 63
    assert [(lin.in_features, lin.out_features) for lin in m.head] == [(64, 64), (64, 64), (64, 2)]
    assert ActorCritic(IMPROVED).encoder.lstm.input_size == 5


def test_zero_neighbours_give_zero_hidden_state():
    m = ActorCritic(PAPER)
    seq = torch.zeros(2, 3, 3)
    h = m.encoder(seq, torch.tensor([0, 0]))
    assert torch.all(h == 0)


def test_occupancy_map_counts_by_bin_area():
    from dataclasses import replace

    enc = OccupancyEncoder(replace(PAPER, encoder="occupancy"))
    assert enc.out_size == 8 * 25
    # one neighbour at 3.5 m dead ahead (bearing 0), one padding row
    seq = torch.tensor([[[3.5, 0.0, 0.0], [0.0, 0.0, 0.0]]])
    grid = enc(seq, torch.tensor([1])).reshape(8, 25)
    assert grid.sum() > 0 and (grid > 0).sum() == 1
    assert grid[1, 12] == pytest.approx(25 / (np.pi * (4**2 - 3**2)))


@pytest.mark.slow
@pytest.mark.parametrize("encoder", ["lstm", "occupancy"])
def test_training_smoke_run(tmp_path, encoder):
    cfg = TrainConfig(
        preset="improved" if encoder == "lstm" else "paper",
        encoder=encoder,
        episodes=60,
        num_envs=16,
        num_steps=16,
        minibatch_size=256,
        update_epochs=1,
        out=str(tmp_path),
        progress=False,
        checkpoint_every=2,
    )
    row = main(cfg)
    assert row["episodes"] >= 60
    lines = (tmp_path / "log.csv").read_text().splitlines()
    assert lines[0].startswith("update,episodes")
    assert (tmp_path / "curve.png").exists() and (tmp_path / "final.pt").exists()
    if encoder == "lstm":
        pol = GuidancePolicy.load(tmp_path / "final.npz")
        assert pol.config["trained_episodes"] >= 60
        out = tmp_path / "again.npz"
        assert export_cli([str(tmp_path / "final.pt"), str(out)]) == 0
        with np.load(out) as z:
            assert json.loads(str(z["config"]))["encoding"] == "sincos"
            assert all(z[k].dtype == np.float32 for k in z.files if k != "config")


def test_every_train_flag_has_help(capsys):
    from comms.cli_options import field_docs
    from policy.train import cli

    docs = field_docs(TrainConfig)
    assert set(docs) == {f.name for f in dataclasses.fields(TrainConfig)}, (
        "a field without a docstring"
    )
    with pytest.raises(SystemExit):
        cli(["--help"])
    assert "Adam learning rate" in capsys.readouterr().out
