"""A planar body's root slide (dm_control's cheetah, walker and hopper ``rootx``): the physics does not
depend on how far it has slid, so the emulator does not read it (``PhysicalModel.invariant_slides``),
as it does not read a free root's x and y; a slide whose position matters is read as before."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from dm_control import suite

from neuroanimator.artifacts import registry, store
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.training import train as training
from neuroanimator.training.envelope import unbounded
from neuroanimator.training.train import TrainConfig

SUITE = Path(suite.__file__).parent


@pytest.mark.parametrize(
    ("domain", "slides"),
    [
        ("cheetah", ("rootx.pos",)),
        ("walker", ("rootx.pos",)),
        ("hopper", ("rootx.pos",)),  # rootz: vertical above a floor, it matters
        ("swimmer", ("rootx.pos", "rooty.pos")),  # no floor: both ways in its plane
        ("ball_in_cup", ()),  # the ball slides beside its cup: where it is matters
        ("cartpole", ()),  # limited: the rail ends
        ("humanoid", ()),  # a free root, translated as such
    ],
)
def test_root_slides_the_physics_ignores_are_found(domain: str, slides: tuple[str, ...]) -> None:
    model = load_mjcf(SUITE / f"{domain}.xml")
    assert model.frame.slides == slides


def test_the_physics_and_the_emulator_ignore_how_far_the_cheetah_has_slid() -> None:
    model = load_mjcf(SUITE / "cheetah.xml")
    col = model.layout.slice_of("rootx.pos").start
    rng = np.random.default_rng(0)
    s = np.stack([model.mj_model.qpos0.copy() for _ in range(8)])
    s = np.concatenate([s, rng.normal(0, 1, (8, model.state_size - s.shape[1]))], axis=1)
    s[:, 1] = 0.1  # above the floor
    u = rng.uniform(-1, 1, (8, model.num_controls))
    far = s.copy()
    far[:, col] += 40.0
    # MuJoCo: the same motion 40 m on
    nxt, nxt_far = model.step_held(s, u, None, 4), model.step_held(far, u, None, 4)
    np.testing.assert_allclose(nxt_far[:, col] - 40.0, nxt[:, col], atol=1e-9)
    keep = np.arange(model.state_size) != col
    np.testing.assert_allclose(nxt_far[:, keep], nxt[:, keep], atol=1e-9)
    # the emulator reads no column of it, and predicts the same change from either place
    torch.manual_seed(0)
    emu = training.build_emulator(model, TrainConfig(hidden=(16,), progress=False)).eval()
    assert "rootx.pos" not in dict(emu.input_groups) and emu.frame.slides == ("rootx.pos",)
    with torch.no_grad():
        a = emu(torch.as_tensor(s).float(), torch.as_tensor(u).float(), None)
        b = emu(torch.as_tensor(far).float(), torch.as_tensor(u).float(), None)
    torch.testing.assert_close(b[:, col] - 40.0, a[:, col], rtol=0, atol=1e-4)
    torch.testing.assert_close(b[:, torch.as_tensor(keep)], a[:, torch.as_tensor(keep)])
    # its envelope has no bounds along it
    free = unbounded(model.layout, model.frame.translate, model.frame.rotate, model.frame.slides)
    assert free[col] and not free[model.layout.slice_of("rootz.pos").start]


def test_a_spring_on_the_slide_makes_its_place_matter(tmp_path: Path) -> None:
    text = (SUITE / "cheetah.xml").read_text()
    sprung = text.replace('<joint name="rootx" type="slide" axis="1 0 0" class="free"/>',
                          '<joint name="rootx" type="slide" axis="1 0 0" class="free" stiffness="10"/>')  # fmt: skip
    assert sprung != text
    path = tmp_path / "cheetah.xml"
    path.write_text(sprung)
    for asset in ("./common/skybox.xml", "./common/visual.xml", "./common/materials.xml"):
        (tmp_path / asset).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / asset).write_text((SUITE / asset).read_text())
    model = load_mjcf(path)
    assert model.frame.slides == ()
    assert (
        float(
            model.mj_model.jnt_stiffness[
                mujoco.mj_name2id(model.mj_model, mujoco.mjtObj.mjOBJ_JOINT, "rootx")
            ]
        )
        == 10
    )
    assert not unbounded(model.layout, (), False, model.frame.slides)[
        model.layout.slice_of("rootx.pos").start
    ]


def test_a_trained_emulator_records_its_slides_and_loads_with_them(tmp_path: Path) -> None:
    subprocess.run(
        [sys.executable, "-m", "neuroanimator.cli", "train", "--mjcf", str(SUITE / "cheetah.xml"), "--name",
         "cheetah", "--substeps", "4", "--examples", "600", "--epochs", "2", "--hidden", "16",
         "--rollout-steps", "0", "--force", "--quiet", "--out", str(tmp_path)],
        check=True, capture_output=True, timeout=600,
    )  # fmt: skip
    path = registry.resolve(tmp_path, "cheetah", substeps=4)
    manifest = registry.read_manifest(path)
    net = manifest.emulator.only()
    assert manifest.frame.slides == net.frame.slides == ["rootx.pos"]
    assert "rootx.pos" not in net.reads.state and "rootz.pos" in net.reads.state
    envelope = {e.group: e for e in manifest.envelope or []}
    assert envelope["rootx.pos"].low == [None] and envelope["rootz.pos"].low != [None]
    emu = store.load_emulator(path)
    assert isinstance(emu, StructuredEmulator) and emu.frame.slides == ("rootx.pos",)
