"""Tiny-budget trainer smoke runs, the occupancy encoder and export."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from policy.export import cli as export_cli  # noqa: E402
from policy.model import IMPROVED, PAPER, ActorCritic, OccupancyEncoder  # noqa: E402
from policy.observation import Observation  # noqa: E402
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
    from cli.options import field_docs
    from policy.train_cli import cli

    docs = field_docs(TrainConfig)
    assert set(docs) == {f.name for f in dataclasses.fields(TrainConfig)}, (
        "a field without a docstring"
    )
    with pytest.raises(SystemExit):
        cli(["--help"])
    assert "Adam learning rate" in capsys.readouterr().out


@pytest.mark.parametrize(("value", "says"), [("-0.5", "must be in [0, 10]"), ("11", "got 11.0")])
def test_a_bad_filter_margin_is_refused_before_training(value, says, capsys):
    """--filter-margin out of the filter's range: exit 2 with the reason, nothing trained."""
    from policy.train_cli import cli

    with pytest.raises(SystemExit) as exc:
        cli(["--filter-margin", value, "--out", "/nonexistent/never-written"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--filter-margin" in err and says in err


def test_init_from_weights_file_reproduces_the_actor(tmp_path):
    """--init policy.npz: the actor acts as the runtime does with that file; a file of another
    network shape is refused with the reason."""
    from policy.train import load_actor

    model = ActorCritic(IMPROVED)
    load_actor(model, "policy/weights/policy.npz")
    pol = GuidancePolicy.load(safety_filter=False)
    rng = np.random.default_rng(0)
    for k in (0, 1, 4):
        nbr = rng.uniform(-15, 15, (k, 2))
        nbr_h = rng.uniform(-np.pi, np.pi, k)
        a = pol.actor.action(
            Observation.at_rest(np.zeros(2), 0.3, np.array([20.0, 5.0]), nbr, nbr_h)
        )
        from policy import features

        seq, goal_feat, _ = features.observe(
            np.zeros(2), 0.3, np.array([20.0, 5.0]), nbr, nbr_h, pol.obs_cfg
        )
        with torch.no_grad():
            mean = model.actor_mean(
                torch.tensor(seq[None], dtype=torch.float32),
                torch.tensor([k]),
                torch.tensor(goal_feat[None], dtype=torch.float32),
            )[0].numpy()
        np.testing.assert_allclose(a, mean / max(1.0, np.hypot(*mean)), atol=1e-5)
    with pytest.raises(ValueError, match="model config"):
        load_actor(ActorCritic(PAPER), "policy/weights/policy.npz")


def test_straight_action_points_at_the_goal():
    from policy.features import action_to_velocity
    from policy.train import straight_action

    pos, goal = np.array([[1.0, 2.0], [0.0, 0.0]]), np.array([[4.0, 6.0], [-3.0, 0.0]])
    heading = np.array([0.7, -2.0])
    a = straight_action(pos, heading, goal)
    v = action_to_velocity(a.astype(np.float64), heading)
    want = (goal - pos) / np.hypot(*(goal - pos).T)[:, None]
    np.testing.assert_allclose(v, want, atol=1e-6)


@pytest.mark.slow
def test_fine_tune_with_the_filter_in_the_loop(tmp_path):
    """A tiny fine-tune from the shipped weights with the filter in the loop and the lone-vehicle
    anchor runs and exports weights the runtime loads; the critic warm-up leaves the actor as
    it was."""
    from policy.train import load_actor

    base = dict(
        preset="improved",
        episodes=40,
        num_envs=16,
        num_steps=16,
        minibatch_size=256,
        update_epochs=1,
        progress=False,
        init="policy/weights/policy.npz",
        safety_filter=True,
        lone_anchor=1.0,
        delta_cav_m=6.0,
        knee_cav_m=4.0,
    )
    row = main(TrainConfig(**base, out=str(tmp_path / "warm"), critic_warmup_updates=1000))
    assert row["episodes"] >= 40
    assert row["collision"] == 0.0  # the filter flies every command
    shipped, warm = ActorCritic(IMPROVED), ActorCritic(IMPROVED)
    load_actor(shipped, "policy/weights/policy.npz")
    load_actor(warm, str(tmp_path / "warm" / "final.npz"))
    for a, b in zip(shipped.head.parameters(), warm.head.parameters(), strict=True):
        assert torch.equal(a, b)
    main(TrainConfig(**base, out=str(tmp_path / "tuned")))
    tuned = ActorCritic(IMPROVED)
    load_actor(tuned, str(tmp_path / "tuned" / "final.npz"))
    assert not torch.equal(tuned.head[0].weight, shipped.head[0].weight)
    GuidancePolicy.load(tmp_path / "tuned" / "final.npz")


def test_the_shipped_recipe_chains_its_stages_within_one_budget():
    """covey train --recipe shipped: from scratch, then the four fine-tunes with the filter in
    the loop (the last on drifting estimates, told the whole separation), each from the weights
    of the stage before, the budget split between them."""
    from policy.recipe import SHIPPED, stage_configs
    from policy.safety import SafetyConfig

    cfg = TrainConfig(recipe="shipped", out="runs/r", seed=11, threads=1, max_minutes=45.0)
    got = stage_configs(cfg, SHIPPED)
    assert [c.out for c in got] == [
        "runs/r/1-scratch",
        "runs/r/2-filter",
        "runs/r/3-filter-wacc10",
        "runs/r/4-filter-wacc14",
        "runs/r/5-drift",
    ]
    assert got[0].init == "" and not got[0].safety_filter and got[0].ccd
    for before, after in zip(got, got[1:], strict=False):
        assert after.init == f"{before.out}/final.npz"
        assert after.safety_filter and after.conflict_share == 0.5 and after.lone_anchor == 1.0
        assert after.filter_margin == SafetyConfig.margin  # flight's margin, every fine-tune
    assert [c.w_acc for c in got] == [6.0, 6.0, 10.0, 14.0, 14.0]
    assert [c.seed for c in got] == [11, 12, 13, 14, 15]
    assert [c.episodes for c in got] == [120_000, 37_000, 30_000, 30_000, 40_000]
    assert [c.drift_m for c in got] == [0.0, 0.0, 0.0, 0.0, 0.5]
    assert [c.filtered_told_share for c in got] == [None, None, None, None, 1.0]
    assert sum(c.max_minutes for c in got) == pytest.approx(45.0)
    assert {c.threads for c in got} == {1}


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--recipe", "shipped", "--w-acc", "3"], "--recipe shipped sets --w-acc itself"),
        (["--recipe", "fastest"], "--recipe must be one of shipped, got 'fastest'"),
    ],
)
def test_a_recipe_refuses_the_flags_it_sets_and_unknown_recipes(argv, says, capsys):
    from policy.train_cli import cli

    with pytest.raises(SystemExit) as exc:
        cli([*argv, "--out", "/nonexistent/never-written"])
    assert exc.value.code == 2
    assert says in capsys.readouterr().err


@pytest.mark.slow
def test_a_recipe_runs_its_stages_in_turn_and_keeps_the_last_weights(tmp_path):
    """Two tiny stages: each writes its weights, the second starts from the first's, and the
    recipe's final.npz is the last stage's."""
    from policy.recipe import Stage, run

    tiny = (("num_envs", 16), ("num_steps", 16), ("minibatch_size", 256), ("update_epochs", 1))
    stages = (
        Stage("a", 40, 0.5, tiny),
        Stage("b", 40, 0.5, (*tiny, ("safety_filter", True), ("critic_warmup_updates", 1000))),
    )
    cfg = TrainConfig(recipe="shipped", out=str(tmp_path), progress=False, max_minutes=10.0)
    last = run(cfg, stages)
    assert [r["stage"] for r in last["stages"]] == ["a", "b"]
    assert all(r["episodes"] >= 40 for r in last["stages"])
    a, b = (ActorCritic(IMPROVED) for _ in range(2))
    from policy.train import load_actor

    load_actor(a, str(tmp_path / "1-a" / "final.npz"))
    load_actor(b, str(tmp_path / "2-b" / "final.npz"))
    for p, q in zip(a.head.parameters(), b.head.parameters(), strict=True):
        assert torch.equal(p, q)  # stage b only warmed its critic: its actor is stage a's
    assert (tmp_path / "final.npz").read_bytes() == (tmp_path / "2-b" / "final.npz").read_bytes()


def test_a_recipe_gives_the_budget_a_stage_left_unused_to_the_next(tmp_path, monkeypatch):
    """With --max-minutes, a stage that stops by its episodes early hands its unused minutes on:
    stages of 0.5 / 0.25 / 0.25 of 40 min taking 5, 20 and 1 min get 20, 10 + 15 and 10 + 5."""
    from policy import recipe, train

    minutes = iter([5.0, 20.0, 1.0])
    now = [0.0]
    budgets = []

    def fake_main(stage_cfg):  # times a stage without training: the budget arithmetic alone
        budgets.append(stage_cfg.max_minutes)
        now[0] += 60.0 * next(minutes)
        out = Path(stage_cfg.out)
        out.mkdir(parents=True)
        (out / "final.npz").write_bytes(b"weights")
        return {"episodes": stage_cfg.episodes}

    monkeypatch.setattr(train, "main", fake_main)
    stages = tuple(
        recipe.Stage(n, 10, share, ()) for n, share in (("a", 0.5), ("b", 0.25), ("c", 0.25))
    )
    cfg = TrainConfig(recipe="shipped", out=str(tmp_path), max_minutes=40.0)
    recipe.run(cfg, stages, clock_s=lambda: now[0])
    assert budgets == pytest.approx([20.0, 25.0, 15.0])
