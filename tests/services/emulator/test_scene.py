"""What a client draws: geometry from the MJCF, body poses of states (REST and websocket), the MuJoCo
shadow (``shadow``) stepped with the same inputs."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from neuroanimator.catalog import get as physics_get


def test_geometry_lists_bodies_and_geoms(client: TestClient) -> None:
    r = client.get("/models/pendulum-active/geometry")
    assert r.status_code == 200, r.text
    g = r.json()
    assert [b["name"] for b in g["bodies"]] == ["link0", "link1", "link2"]
    assert [b["parent"] for b in g["bodies"]] == [-1, 0, 1]
    geom = g["bodies"][1]["geoms"][0]
    assert geom["type"] == "capsule"
    assert geom["size"][0] == pytest.approx(0.04) and geom["size"][1] == pytest.approx(0.25)
    assert geom["pos"] == pytest.approx([0, 0, -0.25]) and len(geom["rgba"]) == 4
    assert len(g["rest_poses"]) == 3 and g["rest_poses"][2][:3] == pytest.approx([0, 0, -1.0])
    assert g["extent"] > 0 and len(g["center"]) == 3
    lander = client.get("/models/lander/geometry").json()
    assert lander["bodies"][0]["geoms"][0]["type"] == "box"
    assert client.get("/models/nope/geometry").status_code == 404


def test_poses_match_forward_kinematics(client: TestClient) -> None:
    # lander: the body's pose is the state's position and quaternion
    q = np.array([0.9, 0.1, -0.2, 0.3]) / np.linalg.norm([0.9, 0.1, -0.2, 0.3])
    state = [1.0, 2.0, 3.0, *q.tolist(), 0, 0, 0, 0, 0, 0]
    r = client.post("/models/lander/poses", json={"states": [state, state]})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["bodies"] == ["ship"] and np.shape(body["poses"]) == (2, 1, 7)
    assert body["poses"][0][0] == pytest.approx([1, 2, 3, *q.tolist()], abs=1e-6)
    # pendulum: the first joint at 90° swings link1's origin from (0,0,-0.5) to about the x axis
    r = client.post("/models/pendulum-active/poses", json={"states": [[np.pi / 2, 0, 0, 0, 0, 0]]})
    p1 = r.json()["poses"][0][1][:3]
    assert abs(p1[2]) < 1e-6 and abs(abs(p1[0]) - 0.5) < 1e-6


@pytest.mark.parametrize(
    ("body", "code", "field"),
    [
        ({"states": [[0.0] * 5]}, "wrong_length", "states[0]"),
        ({"states": []}, "invalid_request", "states"),
        ({"states": [[0, 0, 0, 0, 0, 0]], "extra": 1}, "invalid_request", "extra"),
    ],
)
def test_poses_bad_input_names_the_field(
    client: TestClient, body: dict[str, Any], code: str, field: str
) -> None:
    r = client.post("/models/pendulum-active/poses", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["error"] == code and r.json()["field"] == field


def test_websocket_poses_and_shadow(client: TestClient) -> None:
    sid = client.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
    start = client.get(f"/sessions/{sid}").json()["state"]
    with client.websocket_connect(f"/ws/sessions/{sid}?poses=true&shadow=true") as ws:
        started = ws.receive_json()
        assert started["type"] == "started" and started["poses"] and started["shadow"]
        u = [1.0, -0.5, 0.25]
        states = []
        for i in range(3):
            ws.send_json({"type": "step", "controls": u, "seq": i})
            states.append(ws.receive_json())
        ws.send_json({"type": "start", "shadow": False})
        assert ws.receive_json()["shadow"] is False
        ws.send_json({"type": "step", "controls": u})
        plain = ws.receive_json()
    last = states[-1]
    assert len(last["poses"]) == 3 and len(last["poses"][0]) == 7
    assert len(last["shadow"]["poses"]) == 3 and last["shadow"]["diverged"] is False
    # the twin is MuJoCo from the same start under the same held controls
    model = physics_get("pendulum-active")
    s = np.array([start])
    for _ in range(3):
        s = model.step_held(s, np.array([u]), None, 10)
    assert last["shadow"]["state"] == pytest.approx(s[0].tolist(), abs=1e-6)
    # the emulator's poses are the poses of its state
    r = client.post("/models/pendulum-active/poses", json={"states": [last["state"]]}).json()
    assert np.allclose(last["poses"], r["poses"][0], atol=1e-5)
    assert "shadow" not in plain and "poses" in plain


def test_websocket_realtime_shadow(make_client: Callable[..., TestClient]) -> None:
    client = make_client(ws_realtime_scale=0.1)
    sid = client.post("/sessions", json={"model": "lander", "seed": 2}).json()["id"]
    with client.websocket_connect(f"/ws/sessions/{sid}") as ws:
        ws.send_json({"type": "start", "mode": "realtime", "shadow": True, "poses": True})
        assert ws.receive_json()["type"] == "started"
        msgs = [ws.receive_json() for _ in range(4)]
    assert all(m["type"] == "state" and "shadow" in m and len(m["poses"]) == 1 for m in msgs)


def test_binary_format_refuses_poses(client: TestClient) -> None:
    sid = client.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
    with client.websocket_connect(f"/ws/sessions/{sid}") as ws:
        ws.send_json({"type": "start", "format": "binary", "poses": True, "seq": 4})
        err = ws.receive_json()
        assert err["type"] == "error" and err["error"] == "needs_json" and err["seq"] == 4
        ws.send_json({"type": "ping", "seq": 5})
        assert ws.receive_json() == {"type": "pong", "seq": 5}  # still open


def test_mesh_geoms_name_their_file_and_its_placement() -> None:
    """``MeshInfo``: a file's vertex v is at conj(quat) · (scale ∘ v − pos) in the geom's frame, which is
    where MuJoCo puts the compiled mesh (an off-centre, scaled, lopsided mesh, so that every part of the
    placement counts); a material's colour and coefficients come with the geom."""
    import mujoco

    from services.emulator.scene import _geom

    obj = (
        b"v 0 0 0\nv 1 0 0\nv 0 2 0\nv 0 0 3\nv 1 2 3\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 5\nf 2 5 4\nf 3 4 5\n"
    )
    xml = """<mujoco><asset><mesh name="wedge" file="w.obj" scale="2 1 0.5"/>
    <material name="red" rgba="0.9 0.1 0.1 1" emission="0.2"/></asset>
    <worldbody><body><freejoint/><geom type="mesh" mesh="wedge" material="red" pos="1 1 1" euler="10 20 30"/>
    </body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml, {"w.obj": obj})
    info = _geom(m, 0, {"w.obj"})
    assert info.mesh is not None and info.mesh.asset == "w.obj" and info.mesh.name == "wedge"
    assert info.material is not None and info.material.rgba == pytest.approx([0.9, 0.1, 0.1, 1])
    assert info.material.emission == pytest.approx(0.2)
    raw = np.array(
        [[float(x) for x in line.split()[1:]] for line in obj.decode().splitlines() if line[0] == "v"]
    )
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, np.array(info.mesh.quat))
    placed = (raw * info.mesh.scale - info.mesh.pos) @ rot.reshape(3, 3)  # R^T (s ∘ v − p), row by row
    compiled = m.mesh_vert[m.mesh_vertadr[0] : m.mesh_vertadr[0] + m.mesh_vertnum[0]]
    nearest = np.linalg.norm(placed[:, None] - compiled[None], axis=2).min(axis=1)
    assert nearest.max() < 1e-4 and len(compiled) == len(raw)
    assert _geom(m, 0).mesh.asset is None  # type: ignore[union-attr]  # a file the artifact does not have


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    return _quat_mul(_quat_mul(q, np.array([0.0, *v])), q * np.array([1.0, -1.0, -1.0, -1.0]))[1:]


def test_the_dolphin_is_drawn_as_a_skin_that_follows_its_nodes(
    make_client: Callable[..., TestClient],
) -> None:
    """The geometry carries the MJCF's skin; the documented formula applied to the served poses puts
    its vertices where MuJoCo's own skinning does (before inflation), for a bent and moved body."""
    import mujoco

    from neuroanimator.catalog import dolphin

    client = make_client(
        artifacts_dir=Path(__file__).resolve().parents[3] / "artifacts"
    )  # the committed dolphin
    g = client.get("/models/dolphin/geometry").json()
    # a Playground start at rest: MuJoCo's qpos0, where the slide joints' ref puts the nodes
    assert g["rest_state"][:3] == pytest.approx([1.0, 0.0, 0.0]) and len(g["rest_state"]) == 178
    (skin,) = g["skins"]
    names = [b["name"] for b in g["bodies"]]
    vertices = np.asarray(skin["vertices"]).reshape(-1, 3)
    assert vertices.shape == (23, 3) and len(skin["faces"]) == 3 * 40 and skin["inflate"] > 0
    assert [names[b["body"]] for b in skin["bones"]] == dolphin.NODES  # a vertex on each node
    model = physics_get("dolphin")
    rng = np.random.default_rng(3)
    state = model.rest_state()
    state[: 3 * 23] += rng.normal(scale=0.05, size=3 * 23) + np.tile([0.4, -0.2, 0.1], 23)
    poses = np.asarray(
        client.post("/models/dolphin/poses", json={"states": [state.tolist()]}).json()["poses"][0]
    )
    ours = np.zeros_like(vertices)
    for bone in skin["bones"]:
        pos, quat = poses[bone["body"], :3], poses[bone["body"], 3:]
        bind = np.asarray(bone["bindquat"]) * np.array([1.0, -1.0, -1.0, -1.0])
        q = _quat_mul(quat, bind)
        shift = pos - _rotate(q, np.asarray(bone["bindpos"]))
        for v, w in zip(bone["vertices"], bone["weights"], strict=True):
            ours[v] += w * (_rotate(q, vertices[v]) + shift)
    # MuJoCo's skinning of the same state, without the inflation
    m = model.mj_model
    m.skin_inflate[:] = 0.0
    d = mujoco.MjData(m)
    mujoco.mj_setState(m, d, model.to_physics(state[None])[0], mujoco.mjtState.mjSTATE_FULLPHYSICS)
    mujoco.mj_forward(m, d)
    scene = mujoco.MjvScene(m, maxgeom=1000)
    mujoco.mjv_updateScene(
        m, d, mujoco.MjvOption(), None, mujoco.MjvCamera(), mujoco.mjtCatBit.mjCAT_ALL, scene
    )
    theirs = np.asarray(scene.skinvert).reshape(-1, 3)[:23]
    np.testing.assert_allclose(ours, theirs, atol=1e-5)
    np.testing.assert_allclose(ours, dolphin.node_positions(state[None])[0], atol=1e-5)
