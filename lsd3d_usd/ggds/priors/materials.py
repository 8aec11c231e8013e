"""World-space procedural materials per semantic class (for the procedural prior).

The torch reference of the prior's surface: ggds/priors/surface_kernel.py computes the same
in one numba pass (what the prior runs), held to this module bit for bit by the tests.

Each material maps world positions p (n, 3) float64 and unit normals n (n, 3) to
albedo (n, 3) linear RGB, a specular reflectance `spec` (n,) at normal incidence and a
roughness (n,) in (0, 1]. Pure functions of (p, n, settings): 3D-consistent by construction.
Weather / season hints act only on the classes they concern:
  wetness    -> ground surfaces (road, lane_marking, crosswalk, curb, sidewalk): darker, glossy,
                puddles on the road;
  snow_cover -> up-facing surfaces of every class (a vertical façade stays as it is);
  vegetation -> vegetation and terrain only (green / autumn / bare / snow).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from lsd3d_usd.ggds.priors import noise
from lsd3d_usd.semantics import CLASS_ID

GROUND_CLASSES = ("road", "lane_marking", "crosswalk", "curb", "sidewalk")


@dataclass
class MaterialSettings:
    seed: int = 0
    floor_height: float = 3.2        # storey height of façades (m), as the proxy's buildings
    ground_z: float = 0.0            # world z of the street level (façade floor grid origin)
    window_spacing: float = 2.6      # horizontal window pitch on façades (m)
    wetness: float = 0.0
    snow_cover: float = 0.0
    vegetation: str = "green"


@dataclass
class Material:
    albedo: torch.Tensor
    spec: torch.Tensor
    rough: torch.Tensor


def _rgb(*v, n=1):
    return torch.tensor(v, dtype=torch.float32).expand(n, 3)


def _lerp(a, b, w):
    w = w[..., None] if w.ndim == a.ndim - 1 else w
    return a + (b - a) * w


def _smoothstep(e0, e1, x):
    x = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _consts(n, spec, rough):
    return torch.full((n,), spec), torch.full((n,), rough)


def asphalt(p, nrm, s: MaterialSettings) -> Material:
    n = p.shape[0]
    xy = p[:, :2]
    aggregate = noise.value_noise(xy / 0.012, seed=s.seed + 1)            # ~1 cm stones
    fine = noise.value_noise(xy / 0.05, seed=s.seed + 2)
    wear = noise.fbm(xy / 3.0, octaves=3, seed=s.seed + 3)                 # polished / patched areas
    patch = _smoothstep(0.62, 0.66, noise.fbm(xy / 9.0, octaves=2, seed=s.seed + 4))
    crack_n = noise.fbm(xy / 1.7, octaves=3, seed=s.seed + 5)
    crack = 1.0 - _smoothstep(0.0, 0.012, (crack_n - 0.5).abs())            # thin dark lines
    g = 0.075 + 0.05 * (aggregate - 0.5) + 0.02 * (fine - 0.5) + 0.035 * (wear - 0.5)
    g = g * (1.0 - 0.25 * patch) * (1.0 - 0.45 * crack)
    albedo = torch.stack([g, g * 1.0, g * 1.04], -1)
    spec, rough = _consts(n, 0.03, 0.8)
    return Material(albedo, spec, rough)


def paint(p, nrm, s: MaterialSettings) -> Material:
    base = asphalt(p, nrm, s)
    xy = p[:, :2]
    wear = noise.fbm(xy / 0.4, octaves=3, seed=s.seed + 11)
    cover = _smoothstep(0.25, 0.4, wear)                                    # worn-through spots
    speck = noise.value_noise(xy / 0.01, seed=s.seed + 12)
    white = (0.70 + 0.08 * (speck - 0.5))[:, None] * torch.tensor([1.0, 1.0, 0.97])
    albedo = _lerp(base.albedo, white, cover)
    return Material(albedo, torch.full_like(cover, 0.04), torch.full_like(cover, 0.6))


def concrete(p, nrm, s: MaterialSettings, joint: float = 1.0, tone: float = 0.38) -> Material:
    n = p.shape[0]
    xy = p[:, :2]
    grain = noise.fbm(p / 0.05, octaves=2, seed=s.seed + 21)
    stain = noise.fbm(xy / 2.0, octaves=3, seed=s.seed + 22)
    # joints every `joint` metres along world x and y
    fx = (p[:, 0] / joint) % 1.0
    fy = (p[:, 1] / joint) % 1.0
    dist = torch.minimum(torch.minimum(fx, 1 - fx), torch.minimum(fy, 1 - fy)).float() * joint
    groove = 1.0 - _smoothstep(0.004, 0.012, dist)
    g = tone * (1.0 + 0.15 * (grain - 0.5) + 0.25 * (stain - 0.5)) * (1.0 - 0.5 * groove)
    albedo = torch.stack([g, g * 0.98, g * 0.94], -1)
    spec, rough = _consts(n, 0.03, 0.85)
    return Material(albedo, spec, rough)


def paving(p, nrm, s: MaterialSettings) -> Material:
    """Sidewalk: 0.5 m slabs with a per-slab tint and grout lines."""
    m = concrete(p, nrm, s, joint=0.5, tone=0.34)
    c = noise.cell(p[:, :2], 0.5)
    tint = noise.hash_float(c[:, 0], c[:, 1], seed=s.seed + 31)
    m.albedo = m.albedo * (0.88 + 0.24 * tint)[:, None]
    return m


FACADE_PALETTE = torch.tensor([
    (0.42, 0.22, 0.15),   # red brick
    (0.55, 0.47, 0.36),   # beige render
    (0.36, 0.36, 0.35),   # grey concrete
    (0.62, 0.60, 0.56),   # white-ish render
    (0.45, 0.32, 0.22),   # brown brick
])


# Layouts put walls on round coordinates. The cells that pick a wall's building (its tone and
# window pitch) are counted from this shifted origin so that no cell boundary falls on such a
# wall: on one, the float noise of the G-buffer's world positions flipped the building per pixel
# and between views, and GGDS averaged the disagreeing targets into blotches (docs/ggds.md).
WALL_CELL_SHIFT_M = 0.618


def facade(p, nrm, s: MaterialSettings) -> Material:
    """Walls with a window grid on storeys of floor_height; roofs on up-facing faces."""
    n = p.shape[0]
    # façade coordinates: u along the wall (horizontal tangent), v = height above street level
    t = torch.stack([-nrm[:, 1], nrm[:, 0]], -1)
    tl = t.norm(dim=-1, keepdim=True)
    t = torch.where(tl > 1e-3, t / tl.clamp_min(1e-3), torch.tensor([1.0, 0.0]))
    u = (p[:, 0] * t[:, 0].double() + p[:, 1] * t[:, 1].double())
    off = (p[:, 0] * nrm[:, 0].double() + p[:, 1] * nrm[:, 1].double())       # wall plane offset
    # one "building" per 16 m of frontage (of one wall plane): its own wall tone and window pitch
    plane = noise.cell(off + WALL_CELL_SHIFT_M, 2.0)
    bid = noise.hash_float(noise.cell(u, 16.0), plane, (nrm[:, :2] * 4).round().long().sum(-1),
                           seed=s.seed + 40)
    tone = noise.hash_float(noise.cell(u, 16.0), plane, seed=s.seed + 41)
    wall = FACADE_PALETTE[(tone * len(FACADE_PALETTE)).long().clamp_max(len(FACADE_PALETTE) - 1)]
    wall = wall * (0.85 + 0.3 * bid)[:, None]
    wall = wall * (1.0 + 0.12 * (noise.fbm(p / 0.15, octaves=2, seed=s.seed + 42) - 0.5))[:, None]
    spacing = s.window_spacing * (0.8 + 0.4 * bid).double()
    v = p[:, 2] - s.ground_z
    storey = torch.floor(v / s.floor_height)
    fv = ((v / s.floor_height) % 1.0).float()                  # position within the storey
    col = torch.floor(u / spacing)
    fu = ((u / spacing) % 1.0).float()
    ground = storey < 1
    # windows: 50 % of the pitch wide; 30-80 % of the storey tall (shop fronts: 5-85 %, 75 %)
    half_w = torch.where(ground, torch.tensor(0.375), torch.tensor(0.25))
    v0 = torch.where(ground, torch.tensor(0.05), torch.tensor(0.30))
    v1 = torch.where(ground, torch.tensor(0.85), torch.tensor(0.80))
    du = (fu - 0.5).abs()
    win = ((du < half_w) & (fv > v0) & (fv < v1)).float()
    frame = ((du < half_w + 0.03) & (fv > v0 - 0.03) & (fv < v1 + 0.02)).float() - win
    cid = noise.hash_float(col, storey.long(), noise.cell(p[:, :2] + WALL_CELL_SHIFT_M, 40.0).sum(-1),
                           seed=s.seed + 43)
    glass = torch.tensor([0.05, 0.06, 0.07]) * (0.6 + 0.8 * cid)[:, None]
    curtain = (cid > 0.8).float()[:, None] * torch.tensor([0.25, 0.22, 0.18])
    albedo = _lerp(wall, glass + curtain, win)
    albedo = _lerp(albedo, torch.tensor([0.55, 0.55, 0.53]).expand(n, 3), frame.clamp(0, 1) * 0.7)
    # storey ledge
    ledge = (fv < 0.04).float() * (~ground).float()
    albedo = albedo * (1.0 - 0.25 * ledge)[:, None]
    plinth = (v < 0.5).float() * (1 - win)                     # darker, dirtier base of the wall
    albedo = albedo * (1.0 - 0.35 * plinth)[:, None]
    spec = 0.03 + 0.06 * win
    rough = 0.85 - 0.8 * win
    # roofs (up-facing): dark bitumen / gravel
    roof = _smoothstep(0.6, 0.8, nrm[:, 2])
    roof_alb = (0.12 + 0.05 * noise.value_noise(p[:, :2] / 0.05, seed=s.seed + 44))[:, None].expand(n, 3)
    albedo = _lerp(albedo, roof_alb, roof)
    return Material(albedo, _lerp(spec, torch.full_like(spec, 0.03), roof),
                    _lerp(rough, torch.full_like(rough, 0.9), roof))


FOLIAGE = {
    "green": ((0.05, 0.16, 0.03), (0.14, 0.26, 0.05)),
    "autumn": ((0.35, 0.12, 0.02), (0.55, 0.38, 0.05)),
    "bare": ((0.12, 0.09, 0.07), (0.22, 0.18, 0.14)),
    "snow": ((0.10, 0.09, 0.08), (0.70, 0.72, 0.75)),
}
GRASS = {
    "green": ((0.07, 0.15, 0.03), (0.20, 0.15, 0.08)),
    "autumn": ((0.22, 0.19, 0.06), (0.22, 0.15, 0.08)),
    "bare": ((0.20, 0.17, 0.10), (0.16, 0.12, 0.08)),
    "snow": ((0.75, 0.77, 0.80), (0.55, 0.55, 0.57)),
}


def foliage(p, nrm, s: MaterialSettings) -> Material:
    n = p.shape[0]
    clump = noise.fbm(p / 0.6, octaves=3, seed=s.seed + 51)
    leaf = noise.value_noise(p / 0.05, seed=s.seed + 52)
    a, b = (torch.tensor(c) for c in FOLIAGE[s.vegetation])
    albedo = _lerp(a.expand(n, 3), b.expand(n, 3), _smoothstep(0.3, 0.75, clump))
    shade = 0.55 + 0.45 * _smoothstep(0.25, 0.7, clump) * (0.7 + 0.3 * leaf)  # holes / inner shadow
    albedo = albedo * shade[:, None]
    spec, rough = _consts(n, 0.02, 0.7)
    return Material(albedo, spec, rough)


def terrain(p, nrm, s: MaterialSettings) -> Material:
    n = p.shape[0]
    xy = p[:, :2]
    mix = _smoothstep(0.55, 0.7, noise.fbm(xy / 4.0, octaves=4, seed=s.seed + 61))  # soil patches
    blade = noise.value_noise(xy / 0.03, seed=s.seed + 62)
    a, b = (torch.tensor(c) for c in GRASS[s.vegetation])
    albedo = _lerp(a.expand(n, 3), b.expand(n, 3), mix) * (0.75 + 0.5 * blade)[:, None]
    spec, rough = _consts(n, 0.02, 0.9)
    return Material(albedo, spec, rough)


CAR_COLORS = torch.tensor([
    (0.75, 0.75, 0.75), (0.02, 0.02, 0.02), (0.45, 0.46, 0.48), (0.18, 0.18, 0.19),
    (0.45, 0.03, 0.02), (0.03, 0.08, 0.30), (0.70, 0.70, 0.68), (0.10, 0.15, 0.12),
])


def car_paint(p, nrm, s: MaterialSettings) -> Material:
    """One colour per ~5 m cell (a parked car), glossy clear coat; darker glass on steep
    upper faces is not modelled (the proxy has no window geometry)."""
    c = noise.cell(p[:, :2], 5.0)
    k = (noise.hash_float(c[:, 0], c[:, 1], seed=s.seed + 71) * len(CAR_COLORS)).long().clamp_max(len(CAR_COLORS) - 1)
    albedo = CAR_COLORS[k]
    n = p.shape[0]
    spec, rough = _consts(n, 0.05, 0.15)
    return Material(albedo, spec, rough)


POLE_TONE = (0.30, 0.30, 0.31)
TRAFFIC_LIGHT_TONE = (0.05, 0.05, 0.05)
SIGN_COLORS = torch.tensor([(0.55, 0.05, 0.04), (0.03, 0.12, 0.45), (0.70, 0.70, 0.68), (0.60, 0.45, 0.02)])


def metal(p, nrm, s: MaterialSettings, tone=POLE_TONE) -> Material:
    n = p.shape[0]
    g = 1.0 + 0.1 * (noise.value_noise(p / 0.1, seed=s.seed + 81) - 0.5)
    spec, rough = _consts(n, 0.2, 0.4)
    return Material(torch.tensor(tone).expand(n, 3) * g[:, None], spec, rough)


def sign(p, nrm, s: MaterialSettings) -> Material:
    n = p.shape[0]
    c = noise.cell(p, 3.0)
    k = noise.hash_float(c[:, 0], c[:, 1], c[:, 2], seed=s.seed + 91)
    albedo = SIGN_COLORS[(k * len(SIGN_COLORS)).long().clamp_max(len(SIGN_COLORS) - 1)]
    spec, rough = _consts(n, 0.06, 0.3)
    return Material(albedo, spec, rough)


def default_material(p, nrm, s: MaterialSettings) -> Material:
    return concrete(p, nrm, s, joint=2.0, tone=0.3)


MATERIALS = {
    CLASS_ID["road"]: asphalt,
    CLASS_ID["lane_marking"]: paint,
    CLASS_ID["crosswalk"]: paint,
    CLASS_ID["curb"]: concrete,
    CLASS_ID["sidewalk"]: paving,
    CLASS_ID["building"]: facade,
    CLASS_ID["vegetation"]: foliage,
    CLASS_ID["vehicle"]: car_paint,
    CLASS_ID["pole"]: metal,
    CLASS_ID["sign"]: sign,
    CLASS_ID["terrain"]: terrain,
    CLASS_ID["traffic_light"]: lambda p, n, s: metal(p, n, s, tone=TRAFFIC_LIGHT_TONE),
}


def apply_weather(cls_id: int, m: Material, p, nrm, s: MaterialSettings) -> tuple[Material, torch.Tensor]:
    """Wetness on ground classes, snow on up-facing surfaces. Returns the material and a
    per-pixel wet mirror factor (0..1) for the caller's reflection term."""
    n = p.shape[0]
    mirror = torch.zeros(n)
    ground = cls_id in (CLASS_ID[c] for c in GROUND_CLASSES)
    if s.wetness > 0 and ground:
        # wet porous surfaces darken (water fills the pores) and gain a clear-coat reflection
        m.albedo = m.albedo * (1.0 - 0.45 * s.wetness)
        m.rough = m.rough * (1.0 - 0.75 * s.wetness)
        mirror = torch.full((n,), 0.5 * s.wetness)
        if cls_id == CLASS_ID["road"]:
            puddle = _smoothstep(0.62 - 0.25 * s.wetness, 0.66 - 0.25 * s.wetness,
                                 1.0 - noise.fbm(p[:, :2] / 2.5, octaves=3, seed=s.seed + 101))
            mirror = torch.maximum(mirror, puddle * s.wetness)
            m.albedo = m.albedo * (1.0 - 0.5 * puddle * s.wetness)[:, None]
    if s.snow_cover > 0:
        up = _smoothstep(0.55, 0.85, nrm[:, 2])
        patch = noise.fbm(p[:, :2] / 1.5, octaves=3, seed=s.seed + 111)
        traffic = 0.6 if ground and cls_id != CLASS_ID["sidewalk"] else 1.0   # cleared roads
        cover = up * _smoothstep(1.0 - s.snow_cover * traffic, 1.15 - s.snow_cover * traffic, patch + 0.15)
        snow = (0.82 + 0.08 * noise.value_noise(p / 0.05, seed=s.seed + 112))[:, None] * torch.tensor([0.96, 0.98, 1.0])
        m.albedo = _lerp(m.albedo, snow, cover)
        m.rough = _lerp(m.rough, torch.full_like(m.rough, 0.8), cover)
        mirror = mirror * (1.0 - cover)
    return m, mirror


def surface_reference(p, nrm, cls, s: MaterialSettings) -> torch.Tensor:
    """(N, 6) float32 of points p (N, 3, float64), unit normals nrm (N, 3) and classes cls
    (N,): albedo clamped to [0, 1], specular reflectance, roughness clamped to [0.02, 1] and
    the wet mirror factor — each class's material with its weather, as the procedural prior
    clamps them; surface_kernel.surface_properties computes the same."""
    cls = torch.as_tensor(cls).long().reshape(-1)
    out = torch.zeros(len(cls), 6)
    for cid in torch.unique(cls).tolist():
        at = (cls == cid).nonzero()[:, 0]
        pc, nc = p[at], nrm[at]
        m, mir = apply_weather(cid, MATERIALS.get(cid, default_material)(pc, nc, s), pc, nc, s)
        out[at] = torch.cat([m.albedo.clamp(0, 1), m.spec[:, None], m.rough.clamp(0.02, 1)[:, None],
                             mir[:, None]], dim=1)
    return out
