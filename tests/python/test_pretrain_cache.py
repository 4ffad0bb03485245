"""The pretraining cache is keyed on the code pretraining runs (Reliability
item 5): one changed byte in one of its sources, or in the physics core,
gives another key, so a policy pretrained by other code is never loaded; and
the key is recorded in the run's config.json. The pretrained world model
is cached beside the policies, and a hit is the same model bit for bit."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from ftc import _core
from ftc.tools.controller import Controller
from ftc.control.agents.ppo import ControllerConfig
import torch

from ftc.learning import offline, pretrain
from ftc.learning.ppo import PPOConfig

PACKAGE = Path(pretrain.__file__).resolve().parents[1]


def _copy(tmp_path: Path) -> tuple[Path, Path]:
    root = tmp_path / "ftc"
    for name in pretrain.FINGERPRINT_FILES:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(PACKAGE / name, root / name)
    core = tmp_path / Path(_core.__file__).name
    shutil.copy(_core.__file__, core)
    return root, core


def _flip_last_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[-1] ^= 0x01
    path.write_bytes(bytes(data))


def test_one_changed_byte_changes_the_key(tmp_path):
    root, core = _copy(tmp_path)
    same = pretrain.code_fingerprint(root, core)
    assert same == pretrain.code_fingerprint(PACKAGE)  # the copy is the code that runs
    settings = ControllerConfig().pretrain_settings()
    before = pretrain.cache_path(str(tmp_path / "cache"), settings, PPOConfig())[0]
    for name in ("learning/ppo.py", "plant/reward.py"):
        _flip_last_byte(root / name)
        changed = pretrain.code_fingerprint(root, core)
        assert changed != same, name
        _flip_last_byte(root / name)
        assert pretrain.code_fingerprint(root, core) == same
    _flip_last_byte(core)
    assert pretrain.code_fingerprint(root, core) != same


def test_a_stale_entry_is_a_miss(tmp_path, monkeypatch):
    settings = ControllerConfig().pretrain_settings()
    path, _ = pretrain.cache_path(str(tmp_path), settings, PPOConfig())
    monkeypatch.setattr(pretrain, "code_fingerprint", lambda *a, **k: "other-code")
    other, _ = pretrain.cache_path(str(tmp_path), settings, PPOConfig())
    assert other != path and other.parent == path.parent


def test_the_key_is_in_config_json(tmp_path, scenarios):
    cfg = ControllerConfig(out=str(tmp_path), scenario=str(scenarios / "single.toml"),
                           intervals=1, steps_per_interval=64, update_every=64, pretrain=True,
                           pretrain_max_steps=1024, pretrain_envs=2, pretrain_rollout=32,
                           offline=False, link="core", quiet=True,
                           pretrain_cache=str(tmp_path / "cache"))
    Controller(cfg, PPOConfig()).run()
    doc = json.loads((tmp_path / "config.json").read_text())
    assert doc["pretrain_code"] == pretrain.code_fingerprint()


def _model_tensors(model) -> dict:
    return {k: v.clone() for k, v in model.state_dict().items()}


def test_the_world_model_cache_returns_the_same_model(tmp_path):
    # A hit must be indistinguishable from pretraining: same weights, normalisers,
    # demand and fit count (the fit count seeds every later refit's split and order).
    fresh, demand, info = offline.pretrained_world_model(4, seed=3)
    assert info["model_pretrain_cached"] == 0
    cache = str(tmp_path / "cache")
    built, demand_built, info_built = offline.pretrained_world_model(4, 3, cache)
    hit, demand_hit, info_hit = offline.pretrained_world_model(4, 3, cache)
    assert (info_built["model_pretrain_cached"], info_hit["model_pretrain_cached"]) == (0, 1)
    assert demand == demand_built == demand_hit
    assert fresh.fits == built.fits == hit.fits == 1
    for key, value in _model_tensors(fresh).items():
        assert torch.equal(value, hit.state_dict()[key]), key
    # another seed is another entry
    offline.pretrained_world_model(4, 4, cache)
    assert len(list((tmp_path / "cache").glob("*.pt"))) == 2


def test_a_corrupt_world_model_entry_is_rebuilt(tmp_path):
    cache = str(tmp_path / "cache")
    offline.pretrained_world_model(4, 3, cache)
    (entry,) = (tmp_path / "cache").glob("*.pt")
    entry.write_bytes(b"not a torch file")
    model, _, info = offline.pretrained_world_model(4, 3, cache)
    assert info["model_pretrain_cached"] == 0
    assert offline.pretrained_world_model(4, 3, cache)[2]["model_pretrain_cached"] == 1
    assert bool(model.fitted)
