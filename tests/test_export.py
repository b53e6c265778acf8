"""ONNX export of the whole structured step, served by ONNX Runtime."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.export.onnx import input_names, to_onnx
from neuroanimator.export.runtime import OnnxEmulator

NAMES = sorted(catalog.CATALOG)
MakeEmulator = Callable[..., StructuredEmulator]
InputsOf = Callable[..., tuple[np.ndarray, np.ndarray | None, np.ndarray | None]]


@pytest.fixture(scope="module")
def exported() -> dict[str, tuple[StructuredEmulator, bytes]]:
    return {}


@pytest.fixture
def export_of(
    exported: dict[str, tuple[StructuredEmulator, bytes]], make_emulator: MakeEmulator
) -> Callable[[str], tuple[StructuredEmulator, bytes]]:
    """The emulator (random weights and statistics) of a catalog model and its ONNX bytes, made once."""

    def get(name: str) -> tuple[StructuredEmulator, bytes]:
        if name not in exported:
            emu = make_emulator(catalog.get(name), seed=5)
            exported[name] = (emu, to_onnx(emu))
        return exported[name]

    return get


def _torch_step(
    emu: StructuredEmulator, s: np.ndarray, u: np.ndarray | None, f: np.ndarray | None
) -> np.ndarray:
    def t(a: np.ndarray | None) -> torch.Tensor | None:
        return None if a is None else torch.from_numpy(a.astype(np.float32))

    with torch.no_grad():
        return emu(t(s), t(u), t(f)).numpy()


@pytest.mark.parametrize("name", NAMES)
def test_onnx_matches_torch_on_realistic_states(
    name: str, export_of: Callable[[str], tuple[StructuredEmulator, bytes]], inputs_of: InputsOf
) -> None:
    emu, data = export_of(name)
    s, u, f = inputs_of(catalog.get(name), 64, seed=21)
    ort_out = OnnxEmulator(data).step(s, u, f)
    torch_out = _torch_step(emu, s, u, f)
    assert ort_out.shape == s.shape
    assert np.all(np.isfinite(ort_out))
    scale = max(1.0, float(np.abs(s).max()))
    assert np.abs(ort_out - torch_out).max() <= 1e-4 * scale


@pytest.mark.parametrize(
    ("name", "inputs"),
    [
        ("pendulum-passive", ["state"]),
        ("pendulum-active", ["state", "controls"]),
        ("pendulum-force", ["state", "controls", "forces"]),
        ("lander", ["state", "controls"]),
        ("truck", ["state", "controls"]),
    ],
)
def test_graph_inputs_and_output_are_named(
    name: str, inputs: list[str], export_of: Callable[[str], tuple[StructuredEmulator, bytes]]
) -> None:
    emu, data = export_of(name)
    graph = onnx.load_from_string(data).graph
    assert [i.name for i in graph.input] == inputs == input_names(emu)
    assert [o.name for o in graph.output] == ["next_state"]
    model = catalog.get(name)
    widths = {"state": model.state_size, "controls": model.num_controls, "forces": model.num_forces}
    for value in [*graph.input, *graph.output]:
        dims = value.type.tensor_type.shape.dim
        assert dims[0].dim_param  # the batch axis is symbolic
        assert dims[1].dim_value == widths.get(value.name, model.state_size)


def test_onnx_model_passes_the_checker(export_of: Callable[[str], tuple[StructuredEmulator, bytes]]) -> None:
    _, data = export_of("lander")
    onnx.checker.check_model(onnx.load_from_string(data))


@pytest.mark.parametrize("name", ["lander", "pendulum-force"])
@pytest.mark.parametrize("batch", [1, 7, 300])
def test_any_batch_size_works(
    name: str, batch: int, export_of: Callable[[str], tuple[StructuredEmulator, bytes]], inputs_of: InputsOf
) -> None:
    emu, data = export_of(name)
    s, u, f = inputs_of(catalog.get(name), batch, seed=batch)
    out = OnnxEmulator(data).step(s, u, f)
    assert out.shape == (batch, s.shape[1])
    np.testing.assert_allclose(out, _torch_step(emu, s, u, f), atol=1e-4 * max(1.0, float(np.abs(s).max())))


@pytest.mark.parametrize("name", ["lander", "truck", "pendulum-force"])
def test_batched_step_equals_loop_of_single_steps(
    name: str, export_of: Callable[[str], tuple[StructuredEmulator, bytes]], inputs_of: InputsOf
) -> None:
    _, data = export_of(name)
    emu = OnnxEmulator(data)
    s, u, f = inputs_of(catalog.get(name), 12, seed=31)
    batched = emu.step(s, u, f)
    for i in range(s.shape[0]):
        one = emu.step(s[i : i + 1], None if u is None else u[i : i + 1], None if f is None else f[i : i + 1])
        np.testing.assert_allclose(one[0], batched[i], rtol=1e-5, atol=1e-5)


def test_single_rows_are_kept_and_threads_do_not_share_buffers(
    export_of: Callable[[str], tuple[StructuredEmulator, bytes]], inputs_of: InputsOf
) -> None:
    """One-row steps go through buffers bound once (per thread): a returned state is the caller's to
    keep after the next step, and threads stepping the same emulator get their own rows."""
    _, data = export_of("pendulum-force")
    emu = OnnxEmulator(data)
    s, u, f = inputs_of(catalog.get("pendulum-force"), 8, seed=3)
    assert u is not None and f is not None
    expected = emu.step(s, u, f)
    kept = [emu.step(s[i : i + 1], u[i : i + 1], f[i : i + 1]) for i in range(8)]
    np.testing.assert_allclose(np.concatenate(kept), expected, rtol=1e-5, atol=1e-5)

    def rows(i: int) -> np.ndarray:
        return np.concatenate([emu.step(s[i : i + 1], u[i : i + 1], f[i : i + 1]) for _ in range(200)])

    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(rows, range(8)))
    for i, got in enumerate(results):
        np.testing.assert_allclose(got, np.repeat(expected[i : i + 1], 200, axis=0), rtol=1e-5, atol=1e-5)


def test_input_sizes_are_read_from_the_graph(
    export_of: Callable[[str], tuple[StructuredEmulator, bytes]],
) -> None:
    _, data = export_of("pendulum-force")
    emu = OnnxEmulator(data)
    assert (emu.state_size, emu.num_controls, emu.num_forces) == (6, 3, 3)
    assert emu.input_names == ["state", "controls", "forces"]


def test_step_without_required_controls_raises(
    export_of: Callable[[str], tuple[StructuredEmulator, bytes]],
) -> None:
    _, data = export_of("lander")
    with pytest.raises(ValueError, match="controls"):
        OnnxEmulator(data).step(catalog.get("lander").rest_state()[None])


def test_step_without_required_forces_raises(
    export_of: Callable[[str], tuple[StructuredEmulator, bytes]],
) -> None:
    _, data = export_of("pendulum-force")
    with pytest.raises(ValueError, match="forces"):
        OnnxEmulator(data).step(np.zeros((1, 6)), np.zeros((1, 3)))


def test_passive_model_steps_on_state_alone(
    export_of: Callable[[str], tuple[StructuredEmulator, bytes]], inputs_of: InputsOf
) -> None:
    emu, data = export_of("pendulum-passive")
    s, _, _ = inputs_of(catalog.get("pendulum-passive"), 4)
    np.testing.assert_allclose(OnnxEmulator(data).step(s), _torch_step(emu, s, None, None), atol=1e-4)


def test_rollout_iterates_the_step(
    export_of: Callable[[str], tuple[StructuredEmulator, bytes]], inputs_of: InputsOf
) -> None:
    _, data = export_of("truck")
    emu = OnnxEmulator(data)
    model = catalog.get("truck")
    s, _, _ = inputs_of(model, 3)
    u = model.typical_controls(np.random.default_rng(0), 3, np.arange(4.0) * 0.5)
    states = emu.rollout(s, u)
    assert states.shape == (3, 5, 6)
    np.testing.assert_allclose(states[:, 0], s.astype(np.float32))
    step = s.astype(np.float32)
    for k in range(4):
        step = emu.step(step, u[:, k])
        np.testing.assert_array_equal(states[:, k + 1], step)


def test_onnx_file_path_loads(
    tmp_path: Path, export_of: Callable[[str], tuple[StructuredEmulator, bytes]]
) -> None:
    _, data = export_of("truck")
    path = tmp_path / "emulator.onnx"
    path.write_bytes(data)
    state = np.zeros((2, 6))
    controls = np.ones((2, 2))
    np.testing.assert_array_equal(
        OnnxEmulator(path).step(state, controls), OnnxEmulator(data).step(state, controls)
    )


def test_wrong_input_width_raises(export_of: Callable[[str], tuple[StructuredEmulator, bytes]]) -> None:
    _, data = export_of("lander")
    emu = OnnxEmulator(data)
    with pytest.raises(ValueError, match="state"):
        emu.step(np.zeros((2, 12)), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="controls"):
        emu.step(np.zeros((2, 13)), np.zeros((2, 3)))


def test_mismatched_rows_raise(export_of: Callable[[str], tuple[StructuredEmulator, bytes]]) -> None:
    _, data = export_of("truck")
    with pytest.raises(ValueError, match="rows"):
        OnnxEmulator(data).step(np.zeros((3, 6)), np.zeros((2, 2)))


def test_non_finite_input_raises(export_of: Callable[[str], tuple[StructuredEmulator, bytes]]) -> None:
    _, data = export_of("truck")
    state = np.zeros((2, 6))
    state[1, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        OnnxEmulator(data).step(state, np.zeros((2, 2)))


def test_inputs_the_model_lacks_are_refused(
    export_of: Callable[[str], tuple[StructuredEmulator, bytes]],
) -> None:
    _, data = export_of("pendulum-passive")
    with pytest.raises(ValueError, match="no controls"):
        OnnxEmulator(data).step(np.zeros((1, 6)), np.ones((1, 3)))
    _, data = export_of("truck")
    with pytest.raises(ValueError, match="no forces"):
        OnnxEmulator(data).step(np.zeros((1, 6)), np.ones((1, 2)), np.ones((1, 1)))


def test_unvalidated_step_gives_the_same_result(
    export_of: Callable[[str], tuple[StructuredEmulator, bytes]], inputs_of: InputsOf
) -> None:
    _, data = export_of("pendulum-force")
    emu = OnnxEmulator(data)
    s, u, f = inputs_of(catalog.get("pendulum-force"), 5)
    np.testing.assert_array_equal(emu.step(s, u, f, validate=False), emu.step(s, u, f))
