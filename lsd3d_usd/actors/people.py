"""Procedural vulnerable road users: pedestrians (adult, broad adult, child) and a cyclist.

Written like the vehicle assets (one model per file under its defaultPrim, Z up, metres,
origin on the ground at the centre of the footprint, +X forward, ``extentsHint``,
``lsd3d:actor:kind``, ``lsd3d:actor:dimensions``) with the UsdSemantics class
``pedestrian`` or ``cyclist``. They are articulated by plain xform ops, so any USD tool
plays them back:

    /Adult                        Xform (class pedestrian)
      Torso, Head                 Mesh
      LeftLeg, RightLeg           Xform: xformOp:translate (hip) + xformOp:rotateY (swing)
        Mesh                      the limb, hanging from its pivot
      LeftArm, RightArm           Xform (shoulder) + rotateY, Mesh below
    /Cyclist                      Xform (class cyclist)
      Frame, Torso, Head, Arms    Mesh
      FrontWheel, RearWheel       Xform: translate (hub) + rotateY (spin), Mesh (tyre + spokes)
      Crank                       Xform (bottom bracket) + rotateY, Mesh (arms + pedals)
      LeftLeg, RightLeg           Xform (hip) + rotateY, Mesh

Each file carries one cycle of its motion as time samples (a stride, a wheel turn) over
``CYCLE_CODES`` time codes, with the rest pose as the default value; the actors layer
overrides the rotate ops of every placed instance with samples driven by the distance it
covers (`gait_angles`, `cyclist_angles`), so feet and wheels keep pace with the ground.
``lsd3d:actor:dimensions`` is the envelope of the whole cycle (swinging limbs included),
the box the behaviour model keeps apart and the sensors label.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pathlib import Path

from pxr import Gf, Usd, UsdGeom

from lsd3d_usd.actors.assets import (
    MeshData,
    _new_asset_stage,
    _root_attrs,
    author_mesh,
)
from lsd3d_usd.proxy.shapes import box, cylinder, ellipsoid
from lsd3d_usd.scene import provenance, save_stage

PEDESTRIAN_CLASS = "pedestrian"
CYCLIST_CLASS = "cyclist"
PEDESTRIAN_KINDS = ("adult", "adult_broad", "child")
CYCLIST_KINDS = ("cyclist",)
CYCLE_CODES = 24.0          # one cycle of the asset's own preview animation (1 s at 24 tcps)

SKIN = np.array([(0.55, 0.38, 0.28), (0.33, 0.20, 0.13), (0.18, 0.11, 0.07),
                 (0.62, 0.47, 0.38)], np.float32)
# Linear clothing colours drawn per instance (shirts / jackets, trousers).
SHIRTS = np.array([(0.60, 0.60, 0.58), (0.05, 0.05, 0.06), (0.50, 0.06, 0.05),
                   (0.05, 0.14, 0.40), (0.10, 0.28, 0.12), (0.55, 0.40, 0.12),
                   (0.30, 0.18, 0.35), (0.70, 0.35, 0.05)], np.float32)
TROUSERS = np.array([(0.04, 0.05, 0.10), (0.03, 0.03, 0.03), (0.25, 0.22, 0.18),
                     (0.10, 0.12, 0.20), (0.35, 0.33, 0.30)], np.float32)
BIKE_PAINT = (0.45, 0.05, 0.04)
TYRE = (0.03, 0.03, 0.03)
METAL = (0.35, 0.35, 0.36)


@dataclass(frozen=True)
class BodySpec:
    """A pedestrian's proportions (m): height, shoulder width, torso depth, hip height."""
    height: float
    shoulders: float
    depth: float
    hip: float
    stride: float            # m covered by one full gait cycle (two steps)
    leg_swing: float         # degrees of leg swing at the reference speed
    arm_swing: float
    shirt: tuple
    trousers: tuple
    skin: tuple


BODIES: dict[str, BodySpec] = {
    "adult": BodySpec(1.75, 0.46, 0.26, 0.90, 1.45, 24.0, 18.0,
                      tuple(SHIRTS[3]), tuple(TROUSERS[0]), tuple(SKIN[0])),
    "adult_broad": BodySpec(1.82, 0.54, 0.34, 0.93, 1.50, 22.0, 16.0,
                            tuple(SHIRTS[1]), tuple(TROUSERS[2]), tuple(SKIN[1])),
    "child": BodySpec(1.20, 0.32, 0.20, 0.60, 1.00, 26.0, 20.0,
                      tuple(SHIRTS[2]), tuple(TROUSERS[3]), tuple(SKIN[3])),
}
REFERENCE_WALK = 1.3         # m/s at which the swing reaches its full amplitude

# Cyclist geometry (m): wheel radius, wheelbase, crank length, reference cadence.
WHEEL_R = 0.34
WHEELBASE = 1.05
CRANK = 0.17
GEAR = 2.6                   # wheel turns per crank turn


# ------------------------------------------------------------------ motion (pure)
def gait_angles(distance, speed, body: BodySpec) -> dict[str, np.ndarray]:
    """Limb swing (degrees, rotateY) of a walker that has covered ``distance`` (m) moving at
    ``speed`` (m/s), per sample: legs in antiphase, arms opposite to the legs; the swing
    fades to the rest pose as the walker stops."""
    d = np.asarray(distance, np.float64)
    amp = np.clip(np.asarray(speed, np.float64) / REFERENCE_WALK, 0.0, 1.0)
    s = np.sin(2 * np.pi * d / body.stride)
    leg = body.leg_swing * amp * s
    arm = body.arm_swing * amp * s
    return {"LeftLeg": leg, "RightLeg": -leg, "LeftArm": -arm, "RightArm": arm}


def cyclist_angles(distance) -> dict[str, np.ndarray]:
    """Wheel spin, crank and leg angles (degrees, rotateY) after riding ``distance`` (m):
    the wheels roll without slipping (a positive rotateY turns a wheel forward, +X, on
    the ground), the crank turns 1/GEAR as fast; the legs follow the pedals."""
    d = np.asarray(distance, np.float64)
    wheel = np.degrees(d / WHEEL_R)
    crank = wheel / GEAR
    c = np.radians(crank)
    return {"FrontWheel": wheel, "RearWheel": wheel, "Crank": crank,
            "LeftLeg": 14.0 * np.sin(c), "RightLeg": -14.0 * np.sin(c)}


# ------------------------------------------------------------------ geometry
def _segment(a, b, t: float, w: float | None = None):
    """A box of cross-section t (x/z) by w (y) from point a to point b."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d = b - a
    L = float(np.linalg.norm(d))
    v, f = box(L, w if w is not None else t, -t / 2, t / 2)      # along x, centred
    v[:, 0] += L / 2
    x = d / L
    up = np.array([0.0, 1.0, 0.0]) if abs(x[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    z = np.cross(x, up)
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    return v @ R.T + a, f


def _merge(parts):
    vs, fs, n = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs).astype(np.int32)


def _col(c, f):
    return np.tile(np.asarray(c, np.float32), (len(f), 1))


@dataclass
class Part:
    """A mesh of a model: ``pivot`` (None: fixed to the root) and vertices relative to it."""
    path: str                 # prim path under the root ("Torso", "LeftLeg/Mesh")
    mesh: MeshData
    pivot: tuple | None = None


def pedestrian_parts(kind: str) -> list[Part]:
    b = BODIES[kind]
    H, hip = b.height, b.hip
    head_r = 0.115 * H / 1.75
    neck = H - 2.05 * head_r
    shoulder_z = neck - 0.04 * H
    leg_w = b.shoulders * 0.36
    arm_w = b.shoulders * 0.2
    tv, tf = box(b.depth, b.shoulders, hip - 0.02, shoulder_z + 0.03)
    hv, hf = ellipsoid(head_r * 0.95, head_r * 0.85, head_r, 1)
    hv[:, 2] += H - head_r
    parts = [Part("Torso", MeshData("Torso", tv, tf, _col(b.shirt, tf))),
             Part("Head", MeshData("Head", hv, hf, _col(b.skin, hf)))]
    # the leg's length: its toe (a corner of the swinging box) just reaches the ground at the
    # extreme of the swing, never below it
    half_d = b.depth * 0.35
    sw = np.radians(np.linspace(0.0, b.leg_swing, 64))
    leg = hip
    for _ in range(3):
        leg = hip - float(np.max(leg * np.cos(sw) + half_d * np.sin(sw)) - leg)
    for side, sgn in (("Left", 1.0), ("Right", -1.0)):
        lv, lf = box(b.depth * 0.7, leg_w, -leg, 0.0)
        parts.append(Part(f"{side}Leg/Mesh", MeshData("Mesh", lv, lf, _col(b.trousers, lf)),
                          (0.0, sgn * (b.shoulders / 2 - leg_w / 2 - 0.01), hip)))
        arm_len = 0.42 * H * 0.8
        av, af = box(arm_w * 0.9, arm_w, -arm_len, 0.0)
        parts.append(Part(f"{side}Arm/Mesh", MeshData("Mesh", av, af, _col(b.shirt, af)),
                          (0.0, sgn * (b.shoulders / 2 + arm_w / 2), shoulder_z)))
    return parts


def cyclist_parts() -> list[Part]:
    rx, fx = -WHEELBASE / 2, WHEELBASE / 2
    bb = np.array([0.0, 0.0, 0.30])                      # bottom bracket
    seat = np.array([-0.22, 0.0, 0.90])
    bar = np.array([0.42, 0.0, 1.00])
    head_tube = np.array([0.38, 0.0, 0.80])
    frame = _merge([_segment(bb, seat, 0.04), _segment(seat, head_tube, 0.035),
                    _segment(bb, head_tube, 0.045), _segment([rx, 0, WHEEL_R], bb, 0.03),
                    _segment([rx, 0, WHEEL_R], seat, 0.03), _segment(head_tube, [fx, 0, WHEEL_R], 0.035),
                    _segment(head_tube, bar, 0.035), _segment(bar + [0, -0.25, 0], bar + [0, 0.25, 0], 0.03)])
    fv, ff = frame
    sv, sf = box(0.24, 0.12, 0.0, 0.05)                   # saddle, moved onto the seat post
    sv += seat
    fv, ff = _merge([(fv, ff), (sv, sf)])
    shirt, trousers, skin = SHIRTS[4], TROUSERS[1], SKIN[0]
    hip = seat + [0.02, 0.0, 0.07]
    shoulder = np.array([0.18, 0.0, 1.42])
    tv, tf = _segment(hip, shoulder, 0.24, 0.40)
    hv, hf = ellipsoid(0.11, 0.10, 0.12, 1)
    hv += [0.26, 0.0, 1.60]
    arms = _merge([_segment(shoulder + [0, s * 0.18, 0], bar + [0, s * 0.2, 0], 0.08) for s in (-1, 1)])
    av, af = arms
    parts = [Part("Frame", MeshData("Frame", fv, ff, _col(BIKE_PAINT, ff))),
             Part("Torso", MeshData("Torso", tv, tf, _col(shirt, tf))),
             Part("Head", MeshData("Head", hv, hf, _col(skin, hf))),
             Part("Arms", MeshData("Arms", av, af, _col(shirt, af)))]
    for name, x in (("FrontWheel", fx), ("RearWheel", rx)):
        # a tyre disc across y plus two spokes, so the spin shows
        v, f = cylinder(WHEEL_R, -0.025, 0.025, segments=16)
        v = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)
        s1 = _segment([-WHEEL_R * 0.95, 0, 0], [WHEEL_R * 0.95, 0, 0], 0.03, 0.07)
        s2 = _segment([0, 0, -WHEEL_R * 0.95], [0, 0, WHEEL_R * 0.95], 0.03, 0.07)
        wv, wf = _merge([(v, f), s1, s2])
        cols = np.concatenate([_col(TYRE, f), _col(METAL, s1[1]), _col(METAL, s2[1])])
        parts.append(Part(f"{name}/Mesh", MeshData("Mesh", wv, wf, cols), (x, 0.0, WHEEL_R)))
    cv, cf = _merge([_segment([0, 0.09, 0], [0, 0.09, -CRANK], 0.03),
                     _segment([0, -0.09, 0], [0, -0.09, CRANK], 0.03),
                     ])
    parts.append(Part("Crank/Mesh", MeshData("Mesh", cv, cf, _col(METAL, cf)), tuple(bb)))
    for side, sgn in (("Left", 1.0), ("Right", -1.0)):
        foot = bb + [0.0, sgn * 0.12, 0.0] - hip
        lv, lf = _segment([0, 0, 0], foot, 0.11)
        parts.append(Part(f"{side}Leg/Mesh", MeshData("Mesh", lv, lf, _col(trousers, lf)),
                          (hip[0], sgn * 0.10, hip[2])))
    return parts


def _posed(parts: list[Part], angles: dict[str, float]) -> np.ndarray:
    """All vertices in the root frame with the pivots rotated by ``angles`` (degrees)."""
    out = []
    for p in parts:
        v = p.mesh.vertices
        if p.pivot is not None:
            a = np.radians(angles.get(p.path.split("/")[0], 0.0))
            c, s = np.cos(a), np.sin(a)
            R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])     # rotateY
            v = v @ R.T + np.asarray(p.pivot)
        out.append(v)
    return np.concatenate(out)


def _cycle(kind: str, n: int = 24) -> list[dict[str, float]]:
    """The angles of one motion cycle in ``n`` samples."""
    if kind in BODIES:
        b = BODIES[kind]
        d = np.linspace(0.0, b.stride, n + 1)
        ang = gait_angles(d, REFERENCE_WALK, b)
    else:
        d = np.linspace(0.0, 2 * np.pi * WHEEL_R * GEAR, n + 1)   # one crank turn
        ang = cyclist_angles(d)
    return [{k: float(v[i]) for k, v in ang.items()} for i in range(n + 1)]


def envelope(parts: list[Part], kind: str) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the model over its whole motion cycle (swinging limbs included)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for ang in _cycle(kind, 48):
        v = _posed(parts, ang)
        lo, hi = np.minimum(lo, v.min(0)), np.maximum(hi, v.max(0))
    return lo, hi


def dimensions(kind: str) -> np.ndarray:
    """length, width, height (m) of a procedural model: its box over the whole motion cycle,
    footprint centred on the origin (as written to ``lsd3d:actor:dimensions``)."""
    lo, hi = envelope(parts_of(kind), kind)
    return np.array([2 * max(-lo[0], hi[0]), 2 * max(-lo[1], hi[1]), hi[2]])


def parts_of(kind: str) -> list[Part]:
    if kind in BODIES:
        return pedestrian_parts(kind)
    if kind in CYCLIST_KINDS:
        return cyclist_parts()
    raise ValueError(f"unknown pedestrian/cyclist kind {kind!r}; choose from "
                     f"{', '.join(PEDESTRIAN_KINDS + CYCLIST_KINDS)}")


def write_person_asset(kind: str, path) -> Path:
    """Write the procedural pedestrian or cyclist ``kind`` as an asset file (atomic)."""
    parts = parts_of(kind)
    cls = PEDESTRIAN_CLASS if kind in BODIES else CYCLIST_CLASS
    name = "".join(w[:1].upper() + w[1:] for w in kind.split("_"))
    stage, root = _new_asset_stage(name, kind)
    cycle = _cycle(kind)
    for p in parts:
        if p.pivot is not None:
            joint = p.path.split("/")[0]
            xf = UsdGeom.Xform.Define(stage, f"/{name}/{joint}")
            xf.AddTranslateOp().Set(Gf.Vec3d(*p.pivot))
            rot = xf.AddRotateYOp()
            rot.Set(0.0)                                           # rest pose (default)
            for i, ang in enumerate(cycle):
                rot.Set(ang[joint], Usd.TimeCode(i * CYCLE_CODES / (len(cycle) - 1)))
        author_mesh(stage, f"/{name}/{p.path}", p.mesh, cls)
    lo, hi = envelope(parts, kind)
    dims = dimensions(kind)
    _root_attrs(root.GetPrim(), kind, dims, cls)
    UsdGeom.ModelAPI(root.GetPrim()).SetExtentsHint([tuple(lo), tuple(hi)])
    stage.SetStartTimeCode(0.0)
    stage.SetEndTimeCode(CYCLE_CODES)
    stage.SetTimeCodesPerSecond(24.0)
    stage.GetRootLayer().documentation = (f"lsd3d-usd procedural {kind} ({cls}; Z up, metres, +X "
                                          f"forward; one motion cycle over time codes 0-{CYCLE_CODES:g})")
    return save_stage(stage, path, provenance("actor-asset", {"kind": kind}))


def joint_names(kind_or_class: str) -> tuple[str, ...]:
    """The animated joints (Xform prims under the root) of a procedural model."""
    if kind_or_class in BODIES or kind_or_class == PEDESTRIAN_CLASS:
        return ("LeftLeg", "RightLeg", "LeftArm", "RightArm")
    return ("FrontWheel", "RearWheel", "Crank", "LeftLeg", "RightLeg")


def write_people_library(folder, kinds=PEDESTRIAN_KINDS + CYCLIST_KINDS, fmt: str = "usda"):
    """Write the procedural pedestrians and cyclist to ``folder/<kind>.<fmt>``."""
    folder = Path(folder)
    return {k: write_person_asset(k, folder / f"{k}.{fmt}") for k in kinds}


__all__ = ["BODIES", "CYCLIST_CLASS", "CYCLIST_KINDS", "PEDESTRIAN_CLASS", "PEDESTRIAN_KINDS",
           "cyclist_angles", "dimensions", "envelope", "gait_angles", "joint_names", "parts_of",
           "write_people_library", "write_person_asset"]
