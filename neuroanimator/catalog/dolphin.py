"""The dolphin (thesis E.4, after Tu and Terzopoulos): a mass-spring body that swims by undulating.

**Body.** 23 point masses: the nose, five square cross-sections of 4 nodes (top-left, top-right,
bottom-left, bottom-right; +x is forward, +z dorsal, +y left) and the two tips of the horizontal
fluke. Each node is a body with three slide joints, so its state is its world position and velocity.
Springs (spatial tendons with stiffness, damping and a spring length: the force on node i is
−(c·e + γ·ė)·r/‖r‖ of E.1) run along the body (the four edges), across it (each section's ring and
its diagonals) and through it (face and body diagonals between sections: the cross-springs that keep
its shape); every node also feels the isotropic water damping −γ_i·ẋ_i of E.1 (joint damping).

**Muscles.** Six actuators: dorsal and ventral, on the three rear intervals of the body. Each is a
pair of muscle springs (the left and right edge of that face) sharing one activation a ∈ [0, 1]. A
muscle spring's force is −c(l − l(a)) − γ·l̇ with l(a) = a·l_c + (1 − a)·l_r, which is
−c(l − l_r) − γ·l̇ (a passive tendon with spring length l_r) plus c·(l_c − l_r)·a: a fixed-gain
actuator on a two-branch (pulley) tendon over both springs of the pair, so one control contracts
both with the same force (``tests/physics/test_dolphin.py`` checks this against a hand computation).

**Water.** No gravity (so no buoyancy either: neutrally buoyant), no contact. The dolphin swims
because water resists motion normal to its surface much more than along it. MuJoCo computes that
resistance natively with its ellipsoid fluid model (``fluidshape="ellipsoid"``: blunt and slender
drag, angular drag, Kutta and Magnus lift, from the water's density and viscosity), but only for
geoms on bodies that rotate; a point mass on slide joints never does. So each quarter of the five
horizontal surface strips (the four intervals between sections and the fluke; left or right, dorsal
or ventral) carries a flat ellipsoid "plate" on a light body hinged at its corner node about the
lateral axis, and three alignment tendons from sites on the plate to neighbouring nodes keep the
plate in the plane of its strip (each tendon lies perpendicular to the body's stretching, so it
holds the plate's pitch without stiffening the muscles). The plate passes the water's force on to
the nodes through its joint and tendons. The plates are mirror-symmetric left to right and top to
bottom: with plates only on the top nodes the same stroke curved down (about 7 m in 60 s), with
them alternating it looped upwards; with all four quarters it swims straight.

Why plates, not a drag computed per face outside MuJoCo: the artifact stores one MJCF from which
every part of the system rebuilds the model, and ``PhysicalModel.simulate`` runs ``mujoco.rollout``
with no Python in the step. A drag force computed in numpy would be lost by any consumer that steps
the MJCF alone, and would need one rollout call per physical step: measured on this machine, one
rollout of 1,000 steps runs about 3,200 steps/s, 1,000 rollouts of one step about 1,200 steps/s,
before any drag is computed. The price of the plates is 20 hinges in the state (a pitch angle and
its rate each), which follow the nodes. Hinges about the lateral (y) axis, not ball joints: the
body swims in its plane of symmetry, so a plate only pitches with its strip; ball joints spent three
rotational degrees of freedom (a quaternion and an angular velocity: 7 state values a plate against 2)
on that one pitch, and measured on 5,000 examples the segment networks' one-step errors fell 10-20×
with hinges (segment 2 0.043 → 0.0029; ``BENCHMARKS.md``) while the stroke swims as far (4.04 m in
60 s with ball joints, 3.87 m with hinges). Each plate weighs 0.5 kg: the lighter a
plate, the more closely it follows its nodes and the easier its state is to emulate (with 1.5 kg
plates segment 3's network had 3× the error), and 0.5 kg is stable at δt = 0.01 s on this body
(some strokes of an earlier, 16× stiffer body diverged with it). The alignment springs are damped
near critically (``ALIGN_DAMPING``): at a sixth of that a plate rang for seconds with a period of
about 1 s, a wobble that was the hardest part of the state to emulate.

**Time scale.** Stiffness and damping are set so that the body's best stroke has a period of
about 4 s: the swim controller has one control point per 2 s (60 variables over 20 s, thesis 6.2)
and the emulator holds controls over 0.5 s super-steps. Scaling every stiffness by 1/16 and every
damping by 1/4 slows all the dynamics 4× exactly (quadratic water drag scales with them): the
stiffer body (c = 2,000 N/m) swam best with a 1 s stroke, at 0.28 m/s; this one swims 0.067 m/s
with a 4 s stroke, and holding the stroke constant over each 0.5 s super-step changes that by 2%
(against 27% for the stiffer body).

State (S = 178): for each node its position (3) and velocity (3), for each plate its pitch (1) and
pitch rate (1), in the order node positions, plate pitches, node velocities, plate pitch rates (``NODE_POS`` and ``NODE_VEL`` slice the nodes' part). δt = 0.01 s, implicitfast integration.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from neuroanimator.core.model_spec import (
    ControlInfo,
    HierarchyPart,
    HingeAlignment,
    InitialStates,
    ModelSpec,
    SpringRegularizer,
    TravellingWaves,
)
from neuroanimator.core.state import StateGroup, StateLayout
from neuroanimator.goals.spec import Task

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel

FloatArray = NDArray[np.float64]

TIMESTEP = 0.01
CORNERS = ("tl", "tr", "bl", "br")  # top-left (+y, +z), top-right (−y, +z), bottom-left, bottom-right
# cross-sections: x along the body, half-width (y), half-height (z), mass of each of its 4 nodes
SECTIONS = (
    (0.70, 0.15, 0.17, 6.0),
    (0.30, 0.20, 0.22, 8.0),
    (-0.10, 0.17, 0.19, 7.0),
    (-0.45, 0.11, 0.12, 4.0),
    (-0.75, 0.05, 0.05, 2.0),
)
NOSE = (1.00, 3.0)  # x, mass
FLUKE = (-1.00, 0.30, 1.5)  # x, half-span, mass of each tip
BODY_LENGTH = NOSE[0] - FLUKE[0]

STIFFNESS = 125.0  # N/m, every body spring
DAMPING = 5.0  # N·s/m, every body spring
NODE_DAMPING = 0.125  # N·s/m, isotropic water damping of each node (γ_i of E.1)
MUSCLE_CONTRACTION = 0.7  # l_c / l_r of every muscle spring
MUSCLE_INTERVALS = (1, 2, 3)  # the body intervals (section k to k + 1) that carry muscles
WATER_DENSITY = 1000.0
WATER_VISCOSITY = 0.0009
PLATE_MASS = 0.5
ALIGN_STIFFNESS = 31.25
ALIGN_DAMPING = 7.5  # N·s/m: near critical damping of a plate on its alignment springs (see below)
PLATE_DAMPING = 0.0025  # N·m·s, the plates' hinges
ALIGN_OFFSET = 0.1  # length of an alignment tendon at rest, perpendicular to the body's stretching


def node_names() -> list[str]:
    """The 23 nodes in state order: nose, sections 1–5 (tl, tr, bl, br), fluke tips left, right."""
    return ["nose"] + [f"s{k}{c}" for k in range(1, 6) for c in CORNERS] + ["fluke_l", "fluke_r"]


NODES = node_names()
NUM_NODES = len(NODES)


def rest_positions() -> FloatArray:
    """(23, 3) node positions at rest, in state order."""
    out = [[NOSE[0], 0.0, 0.0]]
    for x, w, h, _ in SECTIONS:
        out += [[x, w, h], [x, -w, h], [x, w, -h], [x, -w, -h]]
    out += [[FLUKE[0], FLUKE[1], 0.0], [FLUKE[0], -FLUKE[1], 0.0]]
    return np.asarray(out, dtype=np.float64)


def node_masses() -> FloatArray:
    return np.asarray(
        [NOSE[1]] + [s[3] for s in SECTIONS for _ in CORNERS] + [FLUKE[2], FLUKE[2]], dtype=np.float64
    )


def _idx(name: str) -> int:
    return NODES.index(name)


def spring_pairs() -> list[tuple[int, int]]:
    """The body's springs as node pairs (i, j), muscles included (``muscle_pairs``)."""
    pairs: list[tuple[str, str]] = [("nose", f"s1{c}") for c in CORNERS]
    for k in range(1, 6):
        tl, tr, bl, br = (f"s{k}{c}" for c in CORNERS)
        pairs += [(tl, tr), (bl, br), (tl, bl), (tr, br), (tl, br), (tr, bl)]  # ring and diagonals
    for k in range(1, 5):
        a = {c: f"s{k}{c}" for c in CORNERS}
        b = {c: f"s{k + 1}{c}" for c in CORNERS}
        pairs += [(a[c], b[c]) for c in CORNERS]  # the four edges along the body
        faces = (("tl", "tr"), ("bl", "br"), ("tl", "bl"), ("tr", "br"))
        pairs += [(a[p], b[q]) for p, q in faces] + [(a[q], b[p]) for p, q in faces]  # face diagonals
        pairs += [(a["tl"], b["br"]), (a["tr"], b["bl"]), (a["bl"], b["tr"]), (a["br"], b["tl"])]
    pairs += [(tip, f"s5{c}") for tip in ("fluke_l", "fluke_r") for c in CORNERS]
    pairs.append(("fluke_l", "fluke_r"))
    return [(_idx(i), _idx(j)) for i, j in pairs]


SPRINGS = spring_pairs()


def muscle_pairs() -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """Per actuator, in control order (dorsal_1, ventral_1, dorsal_2, ...), its two muscle springs."""
    out = []
    for k in MUSCLE_INTERVALS:
        for side in ("t", "b"):
            left = (_idx(f"s{k}{side}l"), _idx(f"s{k + 1}{side}l"))
            right = (_idx(f"s{k}{side}r"), _idx(f"s{k + 1}{side}r"))
            out.append((left, right))
    return out


MUSCLES = muscle_pairs()
CONTROL_NAMES = [f"{side}_{n}" for n in range(1, len(MUSCLE_INTERVALS) + 1) for side in ("dorsal", "ventral")]
# A muscle's activation a in [0, 1] (the MJCF's unit and gain: the pulling force, in N per unit).
CONTROL_INFO = {
    f"{side}_{n}": ControlInfo(
        label=f"{side} muscle {n}",
        sign=f"activation from 0 (relaxed) to 1 (fully contracted) of the {side} muscle pair on body interval "
        f"{interval} (cross-section {interval} to {interval + 1}): contracting it bends the body "
        f"{'up' if side == 'dorsal' else 'down'} there",
    )
    for n, interval in enumerate(MUSCLE_INTERVALS, start=1)
    for side in ("dorsal", "ventral")
}


def rest_lengths() -> FloatArray:
    """(m,) rest length of every body spring (muscles relaxed), in ``SPRINGS`` order."""
    p = rest_positions()
    return np.asarray([np.linalg.norm(p[j] - p[i]) for i, j in SPRINGS])


def deformation_energy(positions: NDArray[np.floating]) -> FloatArray:
    """E_d = ½ Σ ((l_c − l_r)/l_r)² over the body's springs (thesis 6.1.3), muscles at their relaxed
    rest length. positions (..., 23, 3) → (...,)."""
    p = np.asarray(positions, dtype=np.float64)
    i, j = np.asarray(SPRINGS).T
    lengths = np.linalg.norm(p[..., j, :] - p[..., i, :], axis=-1)
    strain = (lengths - rest_lengths()) / rest_lengths()
    return np.asarray(0.5 * np.sum(strain**2, axis=-1))


@dataclass(frozen=True)
class Plate:
    """A drag plate over one horizontal strip: hung from ``anchor``; its centre and half-sizes at rest;
    alignment tendons (node, offset of the plate's site from that node at rest)."""

    name: str
    anchor: int
    centre: tuple[float, float, float]
    half: tuple[float, float, float]
    align: tuple[tuple[int, tuple[float, float, float]], ...]


def _left_plates() -> list[Plate]:
    """The left halves: four body strips (section k to k + 1) and the fluke, each hung from its
    top-left node and aligned in pitch, yaw and roll."""
    d = ALIGN_OFFSET
    out = []
    for k in range(1, 5):
        (x0, w0, _, _), (x1, w1, _, _) = SECTIONS[k - 1], SECTIONS[k]
        half_width = (w0 + w1) / 2 + 0.05
        far = _idx(f"s{k + 1}tl")
        out.append(
            Plate(
                name=f"strip{k}_tl",
                anchor=_idx(f"s{k}tl"),
                centre=((x0 + x1) / 2, half_width / 2, 0.0),
                half=(abs(x1 - x0) / 2, half_width / 2, 0.01),
                align=(
                    (far, (0.0, 0.0, d)),  # pitch: the far end's height
                    (far, (0.0, d, 0.0)),  # yaw: the far end's side
                    (_idx(f"s{k}tr"), (0.0, 0.0, d)),  # roll: the other side's height
                ),
            )
        )
    x5 = SECTIONS[4][0]
    out.append(
        Plate(
            name="fluke_plate_tl",
            anchor=_idx("s5tl"),
            centre=((x5 + FLUKE[0]) / 2, FLUKE[1] / 2, 0.0),
            half=((x5 - FLUKE[0]) / 2 + 0.05, FLUKE[1] / 2, 0.01),
            align=(
                (_idx("fluke_l"), (0.0, 0.0, d)),
                (_idx("fluke_l"), (d * math.sqrt(0.5), d * math.sqrt(0.5), 0.0)),
                (_idx("fluke_r"), (0.0, 0.0, d)),
            ),
        )
    )
    return out


def _mirror(plate: Plate, axis: int, name: str) -> Plate:
    """The same plate mirrored across the body's vertical (axis 1: y → −y, left and right nodes
    swapped) or horizontal (axis 2: z → −z, top and bottom nodes swapped) midplane."""
    swap = {"l": "r", "r": "l"} if axis == 1 else {"t": "b", "b": "t"}
    where = -1 if axis == 1 else -2  # the side letter in "s3tl", "fluke_l"

    def node(i: int) -> int:
        n = NODES[i]
        if n.startswith("s") or (axis == 1 and n.startswith("fluke")):
            n = n[:where] + swap[n[where]] + (n[where + 1 :] if where == -2 else "")
        return _idx(n)

    def flip(v: tuple[float, float, float]) -> tuple[float, float, float]:
        out = list(v)
        out[axis] = -out[axis]
        return (out[0], out[1], out[2])

    return Plate(
        name=name,
        anchor=node(plate.anchor),
        centre=flip(plate.centre),
        half=plate.half,
        align=tuple((node(n), flip(off)) for n, off in plate.align),
    )


def plates() -> list[Plate]:
    """Twenty drag plates: each strip's four quarters (left or right, hung from a top or a bottom
    node), mirror-symmetric left to right and top to bottom, so that a symmetric stroke swims
    straight."""
    top_left = _left_plates()
    left = top_left + [_mirror(p, 2, p.name[:-2] + "bl") for p in top_left]
    return left + [_mirror(p, 1, p.name[:-1] + "r") for p in left]


PLATES = plates()


def _v(x: FloatArray | tuple[float, ...]) -> str:
    return " ".join(f"{float(c):.6g}" for c in x)


def _plate_body(plate: Plate, pos: FloatArray) -> list[str]:
    """MJCF lines of a drag plate's body, inside that of its anchor node, from the nodes' rest
    positions ``pos`` (23, 3): its hinge, its ellipsoid (the water's drag) and the sites its
    alignment tendons pull on."""
    node_pos = pos[plate.anchor]
    centre = np.asarray(plate.centre) - node_pos
    return [
        f'      <body name="{plate.name}">',
        f'        <inertial pos="{_v(centre)}" mass="{PLATE_MASS}" diaginertia="{_plate_inertia(plate)}"/>',
        f'        <joint name="{plate.name}" type="hinge" axis="0 1 0" damping="{PLATE_DAMPING}"/>',
        f'        <geom name="{plate.name}" type="ellipsoid" pos="{_v(centre)}" size="{_v(plate.half)}"'
        ' fluidshape="ellipsoid" group="1" rgba="0.3 0.5 0.8 0.3"/>',
        *(
            f'        <site name="{plate.name}_align{a}" pos="{_v(pos[node] + np.asarray(off) - node_pos)}"/>'
            for a, (node, off) in enumerate(plate.align)
        ),
        "      </body>",
    ]


def _node_bodies() -> list[str]:
    """MJCF lines of the nodes' bodies, in state order: each a point mass on three slides, with the
    plates hung from it."""
    pos, mass = rest_positions(), node_masses()
    by_anchor: dict[int, list[Plate]] = {}
    for plate in PLATES:
        by_anchor.setdefault(plate.anchor, []).append(plate)
    bodies = []
    for n, name in enumerate(NODES):
        inner = [
            f'      <inertial pos="0 0 0" mass="{mass[n]:.6g}" diaginertia="1e-4 1e-4 1e-4"/>',
            *(  # ref = the rest coordinate, so that qpos is the node's world position
                f'      <joint name="{name}_{ax}" type="slide" axis="{axis}" ref="{pos[n, a]:.6g}"'
                f' damping="{NODE_DAMPING}"/>'
                for a, (ax, axis) in enumerate((("x", "1 0 0"), ("y", "0 1 0"), ("z", "0 0 1")))
            ),
            f'      <geom name="{name}" type="sphere" size="0.03" rgba="0.35 0.45 0.6 1"/>',
            f'      <site name="{name}" pos="0 0 0"/>',
        ]
        for plate in by_anchor.get(n, []):
            inner += _plate_body(plate, pos)
        bodies += [f'    <body name="{name}" pos="{_v(pos[n])}">', *inner, "    </body>"]
    return bodies


def _tendons() -> list[str]:
    """MJCF lines of the tendons: the body's springs (muscles at their relaxed length), each
    muscle pair's pulley (what its actuator pulls) and the plates' alignment springs."""
    lengths = rest_lengths()
    tendons = []
    muscle_springs = {tuple(s) for pair in MUSCLES for s in pair}
    for s, (i, j) in enumerate(SPRINGS):
        kind = "muscle" if (i, j) in muscle_springs else "spring"
        tendons += [
            f'    <spatial name="{kind}_{NODES[i]}_{NODES[j]}" stiffness="{STIFFNESS}" damping="{DAMPING}"'
            f' springlength="{lengths[s]:.17g}">',
            f'      <site site="{NODES[i]}"/><site site="{NODES[j]}"/>',
            "    </spatial>",
        ]
    for name, (left, right) in zip(CONTROL_NAMES, MUSCLES, strict=True):
        tendons += [
            f'    <spatial name="{name}">',
            f'      <site site="{NODES[left[0]]}"/><site site="{NODES[left[1]]}"/>',
            '      <pulley divisor="1"/>',
            f'      <site site="{NODES[right[0]]}"/><site site="{NODES[right[1]]}"/>',
            "    </spatial>",
        ]
    for plate in PLATES:
        for a, (node, _) in enumerate(plate.align):
            tendons += [
                f'    <spatial name="{plate.name}_align{a}" stiffness="{ALIGN_STIFFNESS}" damping="{ALIGN_DAMPING}"'
                f' springlength="{ALIGN_OFFSET}">',
                f'      <site site="{plate.name}_align{a}"/><site site="{NODES[node]}"/>',
                "    </spatial>",
            ]
    return tendons


def _actuators() -> list[str]:
    """MJCF lines of the muscles' actuators, in control order: each pulls its pair's pulley tendon
    with the force c·(l_c − l_r) per unit of activation."""
    pos = rest_positions()
    actuators = []
    for name, (left, _) in zip(CONTROL_NAMES, MUSCLES, strict=True):
        rest = float(np.linalg.norm(pos[left[1]] - pos[left[0]]))
        gain = STIFFNESS * (MUSCLE_CONTRACTION - 1.0) * rest  # c·(l_c − l_r): contracts
        actuators.append(
            f'    <general name="{name}" tendon="{name}" gainprm="{gain:.17g}" ctrlrange="0 1"/>'
        )
    return actuators


def mjcf() -> str:
    """The dolphin's self-contained MJCF (no files)."""
    return "\n".join(
        [
            "<!-- The dolphin, thesis appendix E.4: generated by neuroanimator/catalog/dolphin.py, whose",
            "     docstring describes the body, its muscles and the water plates. -->",
            '<mujoco model="dolphin">',
            '  <compiler angle="radian" autolimits="true"/>',
            f'  <option timestep="{TIMESTEP}" gravity="0 0 0" density="{WATER_DENSITY}"'
            f' viscosity="{WATER_VISCOSITY}" integrator="implicitfast">',
            '    <flag contact="disable"/>',
            "  </option>",
            '  <default><geom contype="0" conaffinity="0"/></default>',
            "  <worldbody>",
            *_node_bodies(),
            "  </worldbody>",
            "  <tendon>",
            *_tendons(),
            "  </tendon>",
            "  <actuator>",
            *_actuators(),
            "  </actuator>",
            *_skin(),
            "</mujoco>",
        ]
    )


SKIN_INFLATE = 0.02  # m: the surface passes just outside the nodes' spheres (0.03 m)


def skin_faces() -> list[tuple[int, int, int]]:
    """The body's surface as triangles of nodes, wound outwards: the nose to section 1, a band of
    quads between consecutive sections, a cap behind section 5 and a blade to each fluke tip."""
    ring = ["tl", "tr", "br", "bl"]  # around a cross-section: left-top, right-top, right-bottom, left-bottom
    sec = [[_idx(f"s{k}{c}") for c in ring] for k in range(1, 6)]
    tris: list[tuple[int, int, int]] = []
    for a, b in zip(sec[0], sec[0][1:] + sec[0][:1], strict=True):
        tris.append((_idx("nose"), a, b))
    for front, back in itertools.pairwise(sec):
        for i in range(4):
            j = (i + 1) % 4
            tris += [(front[i], back[i], back[j]), (front[i], back[j], front[j])]
    last = sec[-1]
    tris += [(last[0], last[2], last[1]), (last[0], last[3], last[2])]
    tris += [(_idx("s5tl"), _idx("s5bl"), _idx("fluke_l")), (_idx("s5tr"), _idx("fluke_r"), _idx("s5br"))]
    pos = rest_positions()
    out = []
    for t in tris:  # outwards: away from the body's axis, or along x at the caps
        p = pos[list(t)]
        normal = np.cross(p[1] - p[0], p[2] - p[0])
        centre = p.mean(axis=0)
        out_dir = centre - np.array([centre[0], 0.0, 0.0])
        if np.linalg.norm(out_dir) < 1e-9 or abs(normal[0]) > np.linalg.norm(normal[1:]):
            out_dir = np.array([centre[0], 0.0, 0.0])
        out.append(t if normal @ out_dir >= 0 else (t[0], t[2], t[1]))
    return out


def _skin() -> list[str]:
    """The MJCF skin over the nodes (visual only): one vertex per node, each on its node's body."""
    pos = rest_positions()
    bones = [
        f'      <bone body="{name}" bindpos="{_v(pos[n])}" bindquat="1 0 0 0" vertid="{n}" vertweight="1"/>'
        for n, name in enumerate(NODES)
    ]
    return [
        "  <deformable>",
        f'    <skin name="surface" rgba="0.42 0.52 0.62 1" inflate="{SKIN_INFLATE}"'
        f' vertex="{" ".join(_v(p) for p in pos)}" face="{" ".join(f"{a} {b} {c}" for a, b, c in skin_faces())}">',
        *bones,
        "    </skin>",
        "  </deformable>",
    ]


def _plate_inertia(plate: Plate) -> str:
    a, b, c = plate.half
    m = PLATE_MASS
    return _v((m * (b * b + c * c) / 5, m * (a * a + c * c) / 5, m * (a * a + b * b) / 5))


def _qpos_addresses() -> tuple[list[int], list[int], list[int], list[int]]:
    """qpos/qvel addresses of each node's slides and each plate's hinge, in MJCF body order."""
    node_q, node_v, plate_q, plate_v = [0] * NUM_NODES, [0] * NUM_NODES, [0] * len(PLATES), [0] * len(PLATES)
    q = v = 0
    for n in range(NUM_NODES):
        node_q[n], node_v[n] = q, v
        q, v = q + 3, v + 3
        for p, plate in enumerate(PLATES):
            if plate.anchor == n:
                plate_q[p], plate_v[p] = q, v
                q, v = q + 1, v + 1
    return node_q, node_v, plate_q, plate_v


def layout() -> list[StateGroup]:
    """Node positions, plate pitches, node velocities, plate pitch rates."""
    node_q, node_v, plate_q, plate_v = _qpos_addresses()
    xyz = ("x", "y", "z")
    return (
        [
            StateGroup(name=f"{n}.pos", kind="scalar", size=3, source="qpos", address=a, labels=xyz)
            for n, a in zip(NODES, node_q, strict=True)
        ]
        + [
            # a small angle held by springs that never wraps: a scalar, not a periodic angle
            StateGroup(name=f"{p.name}.pitch", kind="scalar", size=1, source="qpos", address=a, labels=("a",))
            for p, a in zip(PLATES, plate_q, strict=True)
        ]
        + [
            StateGroup(name=f"{n}.vel", kind="scalar", size=3, source="qvel", address=a, labels=xyz)
            for n, a in zip(NODES, node_v, strict=True)
        ]
        + [
            StateGroup(name=f"{p.name}.rate", kind="scalar", size=1, source="qvel", address=a, labels=("w",))
            for p, a in zip(PLATES, plate_v, strict=True)
        ]
    )


LAYOUT = layout()
NODE_POS = slice(0, 3 * NUM_NODES)  # node positions in the state vector, (23·3,)
NODE_VEL = slice(3 * NUM_NODES + len(PLATES), 6 * NUM_NODES + len(PLATES))


def node_positions(states: NDArray[np.floating]) -> FloatArray:
    """(..., S) states → (..., 23, 3) node positions."""
    s = np.asarray(states, dtype=np.float64)
    return s[..., NODE_POS].reshape(*s.shape[:-1], NUM_NODES, 3)


def centre_of_mass(states: NDArray[np.floating]) -> FloatArray:
    """(..., S) → (..., 3) the nodes' centre of mass (plates are light and left out)."""
    m = node_masses()
    return np.einsum("...ni,n->...i", node_positions(states), m / m.sum())


def travelling_wave(
    times: NDArray[np.floating], period: float = 4.0, phase_lag: float = math.pi / 6
) -> FloatArray:
    """(T,) times → (T, 6) a travelling wave of contraction, head to tail: the dorsal and ventral
    muscles of interval k are in antiphase, and each interval lags the one ahead by ``phase_lag``."""
    t = np.asarray(times, dtype=np.float64)[:, None]
    k = np.arange(len(MUSCLE_INTERVALS))[None, :]
    wave = np.sin(2 * math.pi * t / period - phase_lag * k)
    out = np.empty((t.shape[0], 2 * len(MUSCLE_INTERVALS)))
    out[:, 0::2] = 0.5 * (1 + wave)  # dorsal
    out[:, 1::2] = 0.5 * (1 - wave)  # ventral
    return out


SEGMENTS = (
    ("head", ["nose", *(f"s1{c}" for c in CORNERS)], 1),
    *((f"segment{k}", [f"s{k}{c}" for c in CORNERS], k) for k in range(2, 6)),
    ("fluke", ["fluke_l", "fluke_r"], 5),
)
"""The six body segments of the hierarchical emulator (thesis Fig. 4.9): name, nodes, and the
cross-section whose top and bottom give the segment's up axis."""


def hierarchy_parts() -> list[HierarchyPart]:
    """The segments as parts of a hierarchical emulator: each its nodes and the plates hung from them;
    centre: the nodes' centre of mass; axes: left (left minus right nodes; the fluke's tips) and up
    (top minus bottom of the segment's cross-section); neighbours: the other segments' nodes that a
    spring, a muscle or one of its plates' alignment tendons attaches to (the forces on a segment
    come from them)."""
    mass = node_masses()
    owner = {n: name for name, nodes, _ in SEGMENTS for n in nodes}
    plates_of: dict[str, list[str]] = {}
    attached: dict[str, set[str]] = {name: set() for name, _, _ in SEGMENTS}
    for plate in PLATES:
        holder = owner[NODES[plate.anchor]]
        plates_of.setdefault(holder, []).append(plate.name)
        attached[holder] |= {NODES[n] for n, _ in plate.align}
    for i, j in SPRINGS:
        attached[owner[NODES[i]]].add(NODES[j])
        attached[owner[NODES[j]]].add(NODES[i])
    parts = []
    for name, nodes, section in SEGMENTS:
        near = [n for n in NODES if n in attached[name] and owner[n] != name]  # in node order
        mine = set(nodes) | set(plates_of.get(name, []))
        groups = [g.name for g in LAYOUT if g.name.split(".")[0] in mine]
        weights = [float(mass[_idx(n)]) for n in nodes]
        left = [f"s{section}tl", f"s{section}bl"] if name != "fluke" else ["fluke_l"]
        right = [f"s{section}tr", f"s{section}br"] if name != "fluke" else ["fluke_r"]
        top, bottom = [f"s{section}tl", f"s{section}tr"], [f"s{section}bl", f"s{section}br"]
        parts.append(
            HierarchyPart(
                name=name,
                groups=groups,
                points=[(f"{n}.pos", f"{n}.vel") for n in nodes],
                centre=[w / sum(weights) for w in weights],
                axis1=[(f"{n}.pos", 1.0 / len(left)) for n in left]
                + [(f"{n}.pos", -1.0 / len(right)) for n in right],
                axis2=[(f"{n}.pos", 0.5) for n in top] + [(f"{n}.pos", -0.5) for n in bottom],
                neighbours=[(f"{n}.pos", f"{n}.vel") for n in near],
            )
        )
    return parts


REGULARIZER_STIFFNESS = STIFFNESS / 4  # softer and more damped than the body (thesis 6.1.3): explicit
REGULARIZER_DAMPING = 2 * DAMPING  # Euler is stable with them at δt, and they only nudge the shape
# On by default (BENCHMARKS.md, "The dolphin's spring regulariser"): two Euler steps of the springs, and
# each plate's pitch moved 30% of the way to its strip's after every super-step. The plates' pull is
# what keeps long swims bounded: a segment's network reads its plates' pitches about the world's y axis
# in a frame that hides the segment's own pitch, and without the pull they drift (2 rad in 60 s) until
# the body runs away. With a global network trained from drifted states (``--state-noise``) the
# emulator then swims 300 s with E_d within 6% of MuJoCo's mean, where without the regulariser it runs
# away; more Euler steps (5, the thesis') change E_d by a percent and cost 14 graph nodes each.
REGULARIZER_STEPS = 2
REGULARIZER_HINGE_PULL = 0.3


def regularizer(steps: int = REGULARIZER_STEPS) -> SpringRegularizer:
    """The body's springs as the emulator's regulariser (thesis 6.1.3): every spring at its rest length,
    the muscle springs' rest lengths moving with their activation as in the body."""
    lengths = rest_lengths()
    index = {pair: s for s, pair in enumerate(SPRINGS)}
    muscles = [
        (index[spring], control, MUSCLE_CONTRACTION * float(lengths[index[spring]]))
        for control, pair in enumerate(MUSCLES)
        for spring in pair
    ]
    pos = rest_positions()
    hinges = []  # each plate's pitch follows the line from its node to the far node its pitch tendon holds
    for plate in PLATES:
        far = plate.align[0][0]
        x, y, z = (float(c) for c in pos[far] - pos[plate.anchor])
        hinges.append(
            HingeAlignment(
                angle=f"{plate.name}.pitch",
                rate=f"{plate.name}.rate",
                anchor=plate.anchor,
                target=far,
                axis=(0.0, 1.0, 0.0),
                rest=(x, y, z),
            )
        )
    return SpringRegularizer(
        steps=steps,
        dt=TIMESTEP,
        stiffness=REGULARIZER_STIFFNESS,
        damping=REGULARIZER_DAMPING,
        points=[(f"{n}.pos", f"{n}.vel") for n in NODES],
        masses=node_masses().tolist(),
        springs=[(i, j, float(lengths[s])) for s, (i, j) in enumerate(SPRINGS)],
        muscles=muscles,
        hinges=hinges,
        hinge_pull=REGULARIZER_HINGE_PULL,
    )


# Half the training runs swim: waves of contraction from head to tail, dorsal and ventral muscles of
# an interval in antiphase (as ``travelling_wave``), of periods around the best stroke's 4 s and the
# swim controller's (its control points 2.2 s apart), blended 4:1 with random activations so that no
# two wave runs are alike. Random activations alone rarely line up into a stroke, and an emulator
# trained on them underrated the strokes its controller found (BENCHMARKS.md, dolphin-swim).
STROKES = TravellingWaves(
    fraction=0.5,
    period_s=(3.0, 8.0),
    lag=(0.0, math.pi / 2),
    amplitude=(0.5, 1.0),
    phase=[0.0, math.pi] * len(MUSCLE_INTERVALS),
    rank=[k for k in range(len(MUSCLE_INTERVALS)) for _ in range(2)],
    blend=0.2,
)


def dolphin() -> PhysicalModel:
    from neuroanimator.sim.model import PhysicalModel  # MuJoCo loads when a model is built

    size = 6 * NUM_NODES + 2 * len(PLATES)
    # Runs start at rest, as a session does. A start with each node moved at random (±2 cm, ±0.1 m/s)
    # rang in modes that swimming never excites: those first super-steps were 1% of the data and held
    # 56-75% of a linear model's error on the node velocities (0.085 against 0.012 from rest).
    rest = np.zeros(size)
    spec = ModelSpec(
        name="dolphin",
        train_at_start=False,  # 178 state variables: minutes of training, not for a start-up
        description="dolphin: 23-node mass-spring body, 6 muscle pairs, swims by water drag (thesis E.4)",
        layout=LAYOUT,
        control_info=CONTROL_INFO,
        # every activation over its whole range, a control point per second: strokes of 2 s period
        # and slower, around the 4 s of the best one and the swim controller's 2 s control points
        control_low=[0.0] * 6,
        control_high=[1.0] * 6,
        control_spacing_s=1.0,
        travelling_waves=STROKES,
        # training runs start from rest; 60 s of typical controls then reach the shapes and speeds
        # of swimming
        initial=InitialStates(low=rest.tolist(), high=rest.tolist()),
        episode_s=60.0,
        translation_invariant=False,
        rotation_invariant=False,
        thesis_hidden=50,
        parts=hierarchy_parts(),
        regularizer=regularizer(),
    )
    return PhysicalModel(mjcf(), spec)


def _rest_state() -> FloatArray:
    """(S,) the body at rest in state order (MuJoCo's qpos0: plates unturned, nothing moving)."""
    pitches = np.zeros(len(PLATES))
    return np.concatenate([rest_positions().ravel(), pitches, np.zeros(3 * NUM_NODES + len(PLATES))])


# Swim forward for 20 s from rest: the distance its nodes' centre of mass moves along +x (each node's
# x weighed by its mass), less a small control effort; no criterion: as far as it can. 60 control
# variables: a point every 2 s (every four super-steps of N^50) for each of the six muscles (thesis
# 6.2-6.3). The centre of mass is a weighted sum of the segments' centres, so the objective depends
# on the global motion alone and BPTT goes through the global network only (thesis 4.4, 5.3.2).
SWIM = Task(
    name="dolphin-swim",
    model="dolphin",
    summary=(
        "Dolphin: from rest, swim as far forward (+x) as possible in 20 s by driving its six muscles; "
        "the objective is the forward distance of the body's centre of mass, less a small control effort."
    ),
    labels=tuple(StateLayout(tuple(LAYOUT)).labels()),
    initial_state=tuple(float(v) for v in _rest_state()),
    target_state=tuple(float(v) for v in _rest_state()),
    state_weights=(0.0,) * (6 * NUM_NODES + 2 * len(PLATES)),
    success=(),
    initial_controls=(0.5,) * len(CONTROL_NAMES),
    mu_u=1e-3,
    mu_s=0.0,
    terms=(
        {
            "term": "forward_distance",
            "weight": 10.0,
            "variables": [f"{n}.pos.x" for n in NODES],
            "direction": (node_masses() / np.linalg.norm(node_masses())).tolist(),
        },
    ),
    # η = 1 (steps up to the whole range): with 0.5 the line search was still descending at the 20th
    # iteration (J −44.1, then −48 by the 30th); with 1 it levels off near −48 by the 16th (BENCHMARKS.md)
    optimizer={"learning_rate": 1.0, "momentum": 0.5, "max_iterations": 20},
    points_per_step=0.25,
)
TASKS = (SWIM,)
