"""--tensorboard DIR: the controller and the MPC over LCM (a launched plant on
a private URL, ttl=0), a resumed run and a tiny experiment write TensorBoard
scalars that are read back with TensorBoard's own EventAccumulator and
checked against metrics.csv and against the plant's recorded LCM traffic;
a bad DIR is refused before anything is written."""

from __future__ import annotations

import csv
import io
from contextlib import redirect_stderr
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from ftc.tools import controller as controller_cli

from ftc.tools import mpc as mpc_cli
from ftc.tools.controller import Controller
from ftc.control.agents.ppo import ControllerConfig
from ftc.control.run.telemetry import NULL_TELEMETRY, Telemetry
from ftc.experiments import cli as experiments_cli
from ftc.learning.ppo import PPOConfig, UpdateStats
from ftc.plant.link import CorePlant, PlantGoneError
from ftc.plant.log import read_log
from ftc.plant.reward import reward_terms

# metrics.csv holds 6 significant digits, TensorBoard float32 (7)
REL = 1e-5
STEPS, UPDATE_EVERY = 128, 64
SHORT_PPO = ["--intervals", "2", "--steps-per-interval", str(STEPS), "--update-every",
             str(UPDATE_EVERY), "--offline-steps", "512", "--offline-envs", "8",
             "--offline-rollout", "32", "--model-episodes", "6", "--seed", "3", "--quiet"]


def scalars(log_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """tag -> [(step, value)] of every event file under log_dir (not its subdirectories)."""
    acc = EventAccumulator(str(log_dir), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path) as f:
        return list(csv.DictReader(f))


def assert_interval_tags_match_csv(tags: dict, rows: list[dict[str, str]], n: int) -> None:
    """Every non-blank metrics.csv cell is the interval/<column> point at the end
    of its interval; blank cells have no point."""
    for column in rows[0]:
        if column == "interval":
            continue
        cells = [(int(r["interval"]), r[column]) for r in rows]
        expected = [((k + 1) * n, float(v)) for k, v in cells if v != ""]
        got = tags.get(f"interval/{column}", [])
        assert [s for s, _ in got] == [s for s, _ in expected], column
        for (_, g), (_, e) in zip(got, expected):
            assert g == pytest.approx(e, rel=REL, abs=1e-9), column


def assert_reward_terms(tags: dict, rows: list[dict[str, str]], n: int) -> None:
    """reward = balance - activity, per interval, and its mean is reward_per_step."""
    steps = [(k + 1) * n for k in range(len(rows))]
    for name in ("reward", "balance", "activity", "abs_cg", "spread"):
        assert [s for s, _ in tags[f"reward/{name}"]] == steps, name
    for i, row in enumerate(rows):
        r, b, a = (tags[f"reward/{x}"][i][1] for x in ("reward", "balance", "activity"))
        assert r == pytest.approx(float(row["reward_per_step"]), rel=REL)
        assert b - a == pytest.approx(r, rel=REL)
        assert 0.0 <= a <= 1.0
        sps = tags["time/steps_per_second"][i][1]
        assert sps == pytest.approx(n / float(row["online_seconds"]), rel=REL)


def test_controller_over_lcm_writes_every_update_and_interval(tmp_path, scenarios):
    out, tb = tmp_path / "run", tmp_path / "tb"
    assert controller_cli.main(["--scenario", str(scenarios / "single.toml"), "--out", str(out),
                                "--tensorboard", str(tb), *SHORT_PPO]) == 0
    tags, rows = scalars(tb), csv_rows(out / "metrics.csv")
    assert len(rows) == 2
    # one point per PPO update, at the operating step it followed
    update_steps = [64, 128, 192, 256]
    assert {t for t in tags if t.startswith("update/")} == {
        f"update/{f}" for f in UpdateStats._fields}
    for name in ("entropy", "approx_kl", "clipfrac", "value_loss", "open_fraction"):
        points = tags[f"update/{name}"]
        assert [s for s, _ in points] == update_steps, name
        # metrics.csv holds the mean of the interval's updates
        for k, row in enumerate(rows):
            mean = np.mean([v for _, v in points[2 * k:2 * k + 2]])
            assert mean == pytest.approx(float(row[name]), rel=REL, abs=1e-9), name
    assert all(v == 16 for _, v in tags["update/gradient_steps"])  # 4 epochs x 64 / 16
    assert_interval_tags_match_csv(tags, rows, STEPS)
    assert_reward_terms(tags, rows, STEPS)
    # the world model's refit and the evaluation episode, one point per interval
    for column in ("model_r2", "model_prior_r2", "model_one_step_rmse", "model_ten_step_rmse",
                   "eval_reward_per_step"):
        assert len(tags[f"interval/{column}"]) == 2, column
    assert all(0.9 < v <= 1.0 for _, v in tags["interval/model_r2"])


def test_mpc_over_lcm_writes_interval_scalars_and_no_updates(tmp_path, scenarios):
    out, tb = tmp_path / "mpc", tmp_path / "tb"
    assert mpc_cli.main(["--method", "oracle-mpc", "--scenario", str(scenarios / "single.toml"),
                         "--out", str(out), "--tensorboard", str(tb), "--intervals", "2",
                         "--steps-per-interval", "64", "--quiet"]) == 0
    tags, rows = scalars(tb), csv_rows(out / "metrics.csv")
    assert not [t for t in tags if t.startswith("update/")]
    assert_interval_tags_match_csv(tags, rows, 64)
    assert_reward_terms(tags, rows, 64)
    assert len(tags["interval/decisions_per_second"]) == 2


class FailingPlant:
    """A core plant that stops answering after ``steps`` operating steps (the
    evaluation episodes' steps are not counted)."""

    def __init__(self, plant: CorePlant, steps: int) -> None:
        self.plant, self.steps = plant, steps

    def reset(self):
        return self.plant.reset()

    def evaluate(self):
        return self.plant.evaluate()

    def step(self, valves):
        o = self.plant.step(valves)
        if not o.evaluation and o.operating_steps > self.steps:
            raise PlantGoneError("test: the plant stops answering")
        return o

    def close(self) -> None:
        self.plant.close()


def test_resume_purges_what_the_interrupted_interval_wrote(tmp_path, scenarios):
    def config(out: Path, tb: Path, **kw) -> ControllerConfig:
        return ControllerConfig(out=str(out), tensorboard=str(tb), link="core", intervals=2,
                                steps_per_interval=STEPS, update_every=UPDATE_EVERY,
                                offline=False, quiet=True, seed=5,
                                scenario=str(scenarios / "single.toml"), **kw)

    ref, tb_ref = tmp_path / "ref", tmp_path / "tb_ref"
    Controller(config(ref, tb_ref), PPOConfig()).run()
    out, tb = tmp_path / "run", tmp_path / "tb"
    cfg = config(out, tb)
    plant = FailingPlant(CorePlant(cfg.scenario, cfg.seed, steps_per_interval=STEPS),
                         STEPS + 100)  # dies in interval 1, after its update at step 192
    with pytest.raises(Exception, match="plant gone at interval 1"):
        Controller(cfg, PPOConfig()).run(plant=plant)
    assert [s for s, _ in scalars(tb)["update/entropy"]] == [64, 128, 192]
    Controller(config(out, tb, resume=str(out)), PPOConfig()).run()
    assert len(list(tb.glob("events.out.tfevents.*"))) == 2
    got, want = scalars(tb), scalars(tb_ref)
    assert sorted(got) == sorted(want)
    for tag in ("update/entropy", "update/approx_kl", "interval/reward_per_step"):
        assert [s for s, _ in got[tag]] == [s for s, _ in want[tag]], tag  # 192 once
        assert [v for _, v in got[tag]] == [v for _, v in want[tag]], tag


def test_experiments_write_one_directory_per_run_matching_its_log(tmp_path):
    out, tb = tmp_path / "exp", tmp_path / "tb"
    code = experiments_cli.main(["single", "--methods", "closed", "ppo-online",
                                 "--intervals", "2", "--steps-per-interval", "64",
                                 "--controller-args", "--update-every 32", "--jobs", "2",
                                 "--out", str(out), "--tensorboard", str(tb)])
    assert code == 0
    runs = sorted(str(p.parent.relative_to(tb)) for p in tb.rglob("events.out.tfevents.*"))
    assert runs == ["single/t00/closed/s0", "single/t00/ppo-online/s0"]
    for key in runs:
        run_dir = out / "runs" / key
        tags, rows = scalars(tb / key), csv_rows(run_dir / "metrics.csv")
        assert_interval_tags_match_csv(tags, rows, 64)
        assert_reward_terms(tags, rows, 64)
        updates = [s for s, _ in tags.get("update/entropy", [])]
        assert updates == ([32, 64, 96, 128] if "ppo" in key else [])
        # the reward terms again, from the plant's recorded LCM traffic
        log = read_log(run_dir / "plant.lcmlog")
        online = ~log.evaluation
        for k in range(2):
            m = online & (log.operating_steps > 64 * k) & (log.operating_steps <= 64 * (k + 1))
            assert m.sum() == 64
            terms = reward_terms(log.level[m], log.valves[m])
            for name, values in (("reward", terms.reward), ("activity", terms.activity),
                                 ("abs_cg", np.abs(terms.cg)), ("spread", terms.spread)):
                assert tags[f"reward/{name}"][k][1] == pytest.approx(
                    float(np.mean(values)), rel=REL, abs=1e-9), (key, name)
        if "closed" in key:
            assert [v for _, v in tags["reward/activity"]] == [0.0, 0.0]


def _refused(main, argv: list[str]) -> str:
    err = io.StringIO()
    with redirect_stderr(err), pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    lines = err.getvalue().strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err.getvalue(), err.getvalue()
    return lines[0]


@pytest.mark.parametrize("where", ["file", "under-file", "empty"])
def test_bad_tensorboard_dir_is_refused_before_anything_is_written(tmp_path, scenarios, where):
    blocker = tmp_path / "blocker"
    blocker.write_text("not a directory\n")
    tb = {"file": str(blocker), "under-file": str(blocker / "tb"), "empty": ""}[where]
    out = tmp_path / "out"
    for tool, main, extra in (
            ("ftc.controller", controller_cli.parse_args, []),
            ("ftc.mpc", mpc_cli.parse_args, ["--method", "oracle-mpc"]),
            ("ftc.experiments", experiments_cli.parse_args, ["single"])):
        argv = [*extra, "--out", str(out), "--tensorboard", tb]
        if tool != "ftc.experiments":
            argv += ["--scenario", str(scenarios / "single.toml")]
        line = _refused(main, argv)
        assert line.startswith(f"{tool}: error:") and "--tensorboard" in line, line
        if where != "empty":
            assert str(blocker) in line, line
        assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker"], "something was written"


def test_without_the_flag_the_hooks_are_the_no_op_base_class(tmp_path, scenarios):
    """The default path: the runner and the agent hold the no-op Telemetry and no
    event file appears anywhere in the run directory."""
    cfg = ControllerConfig(out=str(tmp_path / "run"), link="core", intervals=1,
                           steps_per_interval=64, update_every=32, offline=False, quiet=True,
                           scenario=str(scenarios / "single.toml"))
    runner = Controller(cfg, PPOConfig())
    runner.run()
    assert runner.telemetry is NULL_TELEMETRY and runner.agent.telemetry is NULL_TELEMETRY
    assert type(NULL_TELEMETRY) is Telemetry
    assert not list(tmp_path.rglob("events.out.tfevents.*"))
