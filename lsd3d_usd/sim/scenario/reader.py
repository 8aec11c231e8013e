"""Read an ASAM OpenSCENARIO XML 1.0-1.3 file into dataclasses, safely.

Safety: lxml without entity expansion, DTD loading or network, no huge trees, a size bound
per file; a DOCTYPE declaring entities is refused. Parameters: `ParameterDeclarations`
(scoped to the element declaring them) and `$name` / `${expr}` references are resolved;
an undeclared name is an error. Catalogs: `CatalogReference`s are replaced by the entry
from the catalog directories the file names, which must lie inside the scenario's folder.

Every error is one `InputError` line naming the file, the element and its line. Elements
outside the supported set are kept as `Unsupported` and warned about (`ScenarioWarning`).
"""
from __future__ import annotations

import ast
import copy
import math
import operator
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from lsd3d_usd.errors import InputError

MAX_FILE_BYTES = 32 * 1024 * 1024          # one .xosc or catalog file
MAX_TRAJECTORY_VERTICES = 100_000
MAX_CATALOG_FILES = 200
SRC_ATTR = "_lsd3d_src"                   # marks a catalog entry copied into the tree


class ScenarioWarning(UserWarning):
    """An element the reader or player does not support (named with its file line)."""


# ---------------------------------------------------------------- data

@dataclass
class Position:
    """kind: world, lane, relative_lane, relative_object, relative_world, road."""
    kind: str
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    h: float | None = None
    road_id: str = ""
    lane_id: int = 0
    s: float = 0.0
    offset: float = 0.0
    entity: str = ""             # relative positions: the reference entity
    dx: float = 0.0
    dy: float = 0.0
    ds: float = 0.0
    d_lane: int = 0
    where: str = ""


@dataclass
class Entity:
    name: str
    kind: str                    # "vehicle" or "pedestrian"
    category: str = "car"
    length: float = 4.5
    width: float = 1.8
    height: float = 1.5
    center: tuple = (1.4, 0.0, 0.75)   # bounding box centre relative to the reference point
    where: str = ""


@dataclass
class Dynamics:
    shape: str                   # step, linear, cubic, sinusoidal
    dimension: str               # time, distance, rate
    value: float


@dataclass
class SpeedAction:
    dynamics: Dynamics
    speed: float | None = None           # absolute target
    ref_entity: str = ""                 # relative target
    rel_value: float = 0.0
    rel_type: str = "delta"              # delta or factor
    where: str = ""


@dataclass
class LaneChangeAction:
    dynamics: Dynamics
    lane_id: int | None = None           # absolute target (OpenDRIVE lane id)
    ref_entity: str = ""                 # relative target: lanes left (+) of ref_entity's
    rel_lanes: int = 0
    target_offset: float = 0.0
    where: str = ""


@dataclass
class TeleportAction:
    position: Position
    where: str = ""


@dataclass
class FollowTrajectoryAction:
    vertices: list                       # [(time or None, Position)]
    closed: bool = False
    timing: tuple | None = None          # (domain "absolute"/"relative", scale, offset)
    name: str = ""
    where: str = ""


@dataclass
class AssignRouteAction:
    waypoints: list                      # [Position]
    name: str = ""
    where: str = ""


@dataclass
class SynchronizeAction:
    master: str
    master_position: Position
    position: Position
    final_speed: float | None = None
    where: str = ""


@dataclass
class Unsupported:
    element: str
    where: str = ""


@dataclass
class Condition:
    """kind: the condition element's name (SimulationTimeCondition, ...); params its
    attributes and the reference entity / position; entities: the triggering entities."""
    name: str
    kind: str
    delay: float
    edge: str
    params: dict
    entities: list = field(default_factory=list)
    entity_rule: str = "any"
    where: str = ""


@dataclass
class Trigger:
    groups: list                         # [[Condition]]: OR over groups, AND within one


@dataclass
class PrivateAction:
    """An action for ``actor`` (an entity name; None: the maneuver group's actors)."""
    name: str
    action: object
    actor: str | None = None


@dataclass
class Event:
    name: str
    priority: str
    max_executions: int
    actions: list                        # [PrivateAction]
    start: Trigger | None
    where: str = ""


@dataclass
class Maneuver:
    name: str
    events: list


@dataclass
class ManeuverGroup:
    name: str
    max_executions: int
    actors: list
    maneuvers: list


@dataclass
class Act:
    name: str
    groups: list
    start: Trigger | None
    stop: Trigger | None


@dataclass
class Story:
    name: str
    acts: list


@dataclass
class Scenario:
    path: Path
    version: str
    road_file: Path | None
    entities: dict                       # name -> Entity
    init: dict                           # entity name -> [action]
    stories: list
    stop: Trigger | None
    parameters: dict
    unsupported: list                    # [Unsupported]
    ego_name: str = ""                   # chosen by `choose_ego` (--ego); "": the first entity

    @property
    def ego(self) -> str:
        """The ego's name: the one `choose_ego` named, else the first ScenarioObject (as
        esmini and ScenarioRunner take the first as the hero by default)."""
        return self.ego_name or next(iter(self.entities), "")

    def choose_ego(self, name: str | None) -> None:
        """Make entity ``name`` the ego (None: keep the default)."""
        if name is None:
            return
        if name not in self.entities:
            have = ", ".join(self.entities) or "none"
            raise InputError(f"--ego {name!r}: not an entity of {self.path} (its entities: {have})")
        self.ego_name = name


# ---------------------------------------------------------------- XML

def _parser():
    from lxml import etree
    return etree.XMLParser(resolve_entities=False, no_network=True, huge_tree=False,
                           load_dtd=False, dtd_validation=False, remove_comments=True,
                           remove_pis=True)


def parse_file(path: Path, what: str = "scenario"):
    """The XML root of a file, read safely (one-line InputError otherwise)."""
    from lxml import etree
    if not path.is_file():
        raise InputError(f"{path}: no such {what} file")
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise InputError(f"{path}: {size} bytes, more than the {MAX_FILE_BYTES} allowed for a {what} file")
    try:
        tree = etree.parse(str(path), _parser())
    except etree.XMLSyntaxError as e:
        msg = " ".join(str(e).split())
        raise InputError(f"{path}: not well-formed XML: {msg}") from None
    dt = tree.docinfo.internalDTD
    if dt is not None and (list(dt.iterentities()) or dt.elements()):
        raise InputError(f"{path}: <!DOCTYPE> with entity or element declarations: refused "
                         "(entities are never expanded)")
    for el in tree.iter():
        if not isinstance(el.tag, str):          # an unexpanded entity reference
            raise InputError(f"{path}:{el.sourceline}: entity reference {el!s:.40}: refused")
    return tree.getroot()


class _Ctx:
    def __init__(self, path: Path):
        self.path = path
        self.folder = path.parent.resolve()
        self.unsupported: list[Unsupported] = []

    def where(self, el) -> str:
        src, e = self.path, el
        while e is not None:
            if e.get(SRC_ATTR):
                src = Path(e.get(SRC_ATTR))
                break
            e = e.getparent()
        return f"{src}:{el.sourceline}"

    def error(self, el, msg: str) -> InputError:
        return InputError(f"{self.where(el)}: <{_tag(el)}>: {msg}")

    def unsupported_el(self, el, what: str | None = None) -> Unsupported:
        u = Unsupported(what or _tag(el), self.where(el))
        self.unsupported.append(u)
        warnings.warn(f"{u.where}: <{u.element}> is not supported; ignored", ScenarioWarning,
                      stacklevel=4)
        return u

    def inside(self, el, rel: str, what: str) -> Path:
        p = Path(rel)
        full = (self.path.parent / p).resolve()
        if not full.is_relative_to(self.folder):
            raise self.error(el, f"{what} {rel!r} lies outside the scenario's folder "
                                 f"{self.folder}; only files inside it are read")
        return full


def _tag(el) -> str:
    return el.tag.split("}")[-1] if isinstance(el.tag, str) else str(el)


def _kid(el, name):
    for c in el:
        if isinstance(c.tag, str) and _tag(c) == name:
            return c
    return None


def _kids(el, name):
    return [c for c in el if isinstance(c.tag, str) and _tag(c) == name]


def _only(el):
    kids = [c for c in el if isinstance(c.tag, str)]
    return kids[0] if kids else None


# ---------------------------------------------------------------- parameters

_PARAM = re.compile(r"^\$([A-Za-z_][A-Za-z0-9_]*)$")
_EXPR = re.compile(r"^\$\{(.*)\}$", re.S)
_OPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
        ast.Div: operator.truediv, ast.Mod: operator.mod, ast.Pow: operator.pow,
        ast.USub: operator.neg, ast.UAdd: operator.pos}


def _eval_expr(text: str, lookup) -> str:
    """An OpenSCENARIO 1.1 expression: numbers, $names, + - * / % **, parentheses."""
    src = re.sub(r"\$([A-Za-z_][A-Za-z0-9_]*)", r"_p_\1", text)
    tree = ast.parse(src, mode="eval")

    def ev(n):
        if isinstance(n, ast.Expression):
            return ev(n.body)
        if isinstance(n, ast.Constant) and isinstance(n.value, (int, float)):
            return n.value
        if isinstance(n, ast.Name) and n.id.startswith("_p_"):
            return float(lookup(n.id[3:]))
        if isinstance(n, ast.BinOp) and type(n.op) in _OPS:
            a, b = ev(n.left), ev(n.right)
            if isinstance(n.op, ast.Pow) and abs(b) > 64:
                raise ValueError("exponent too large")
            return _OPS[type(n.op)](a, b)
        if isinstance(n, ast.UnaryOp) and type(n.op) in _OPS:
            return _OPS[type(n.op)](ev(n.operand))
        raise ValueError(f"unsupported expression part {ast.dump(n)[:30]}")
    v = ev(tree)
    return repr(float(v)) if isinstance(v, float) else str(v)


def _resolve_params(ctx: _Ctx, el, scope: dict) -> None:
    """Replace $name / ${expr} attribute values in ``el``'s subtree (scoped declarations)."""
    decl = _kid(el, "ParameterDeclarations")
    if decl is not None:
        scope = dict(scope)
        for d in _kids(decl, "ParameterDeclaration"):
            name = d.get("name")
            _sub_attrs(ctx, d, scope, skip=("name",))
            scope[name] = d.get("value", "")
    if _tag(el) != "ParameterDeclarations":
        _sub_attrs(ctx, el, scope)
    for c in el:
        if isinstance(c.tag, str) and _tag(c) != "ParameterDeclarations" and _tag(c) != "Catalog":
            _resolve_params(ctx, c, scope)


def _sub_attrs(ctx: _Ctx, el, scope: dict, skip=()) -> None:
    for k, v in list(el.attrib.items()):
        if k in skip or not v.startswith("$") or k == SRC_ATTR:
            continue

        def look(name, el=el, k=k):
            if name not in scope:
                raise ctx.error(el, f"attribute {k}: parameter ${name} is not declared "
                                    "(no ParameterDeclaration of that name in scope)")
            return scope[name]
        m = _PARAM.match(v)
        if m:
            el.set(k, look(m.group(1)))
            continue
        m = _EXPR.match(v)
        if m:
            try:
                el.set(k, _eval_expr(m.group(1), look))
            except InputError:
                raise
            except (ValueError, SyntaxError, ZeroDivisionError, OverflowError, TypeError) as e:
                raise ctx.error(el, f"attribute {k}: expression {v[:60]!r}: {e}") from None


# ---------------------------------------------------------------- catalogs

def _catalog_dirs(ctx: _Ctx, root) -> list[Path]:
    locs = _kid(root, "CatalogLocations")
    out = []
    if locs is None:
        return out
    for c in locs:
        if not isinstance(c.tag, str):
            continue
        d = _kid(c, "Directory")
        if d is None or not d.get("path"):
            continue
        p = ctx.inside(d, d.get("path"), "catalog directory")
        out.append(p)
    return out


def _resolve_catalogs(ctx: _Ctx, root, scope: dict) -> None:
    refs = [e for e in root.iter() if isinstance(e.tag, str) and _tag(e) == "CatalogReference"]
    if not refs:
        return
    dirs = _catalog_dirs(ctx, root)
    catalogs: dict[str, object] = {}
    n = 0
    for d in dirs:
        files = sorted(d.glob("*.xosc")) if d.is_dir() else []
        for f in files:
            n += 1
            if n > MAX_CATALOG_FILES:
                raise InputError(f"{d}: more than {MAX_CATALOG_FILES} catalog files")
            if not f.resolve().is_relative_to(ctx.folder):
                raise InputError(f"{f}: catalog file outside the scenario's folder {ctx.folder}")
            croot = parse_file(f, "catalog")
            for cat in _kids(croot, "Catalog"):
                cat.set(SRC_ATTR, str(f))
                catalogs.setdefault(cat.get("name", ""), cat)
    for ref in refs:
        cname, ename = ref.get("catalogName", ""), ref.get("entryName", "")
        cat = catalogs.get(cname)
        if cat is None:
            where = ", ".join(str(d) for d in dirs) or "no CatalogLocations"
            raise ctx.error(ref, f"catalog {cname!r} not found (searched: {where})")
        entry = next((c for c in cat if isinstance(c.tag, str) and c.get("name") == ename), None)
        if entry is None:
            raise ctx.error(ref, f"catalog {cname!r} has no entry {ename!r}")
        new = copy.deepcopy(entry)
        new.set(SRC_ATTR, cat.get(SRC_ATTR))
        # the entry's declared defaults, overridden by the reference's assignments
        local = {}
        decl = _kid(new, "ParameterDeclarations")
        if decl is not None:
            for d in _kids(decl, "ParameterDeclaration"):
                local[d.get("name")] = d.get("value", "")
            new.remove(decl)
        pa = _kid(ref, "ParameterAssignments")
        for a in (_kids(pa, "ParameterAssignment") if pa is not None else []):
            if a.get("parameterRef") not in local:
                raise ctx.error(a, f"catalog entry {ename!r} declares no parameter "
                                   f"{a.get('parameterRef')!r}")
            local[a.get("parameterRef")] = a.get("value", "")
        _resolve_params(ctx, new, {**scope, **local})
        ref.getparent().replace(ref, new)


# ---------------------------------------------------------------- elements

def _num(ctx, el, name, default=None) -> float:
    v = el.get(name)
    if v is None:
        if default is None:
            raise ctx.error(el, f"attribute {name} is missing")
        return default
    try:
        f = float(v)
    except ValueError:
        raise ctx.error(el, f"attribute {name}={v[:40]!r} is not a number") from None
    if not math.isfinite(f):
        raise ctx.error(el, f"attribute {name}={v[:40]!r} is not finite")
    return f


def _int(ctx, el, name, default=None) -> int:
    f = _num(ctx, el, name, None if default is None else float(default))
    if f != int(f):
        raise ctx.error(el, f"attribute {name}={f} is not a whole number")
    return int(f)


def read_position(ctx: _Ctx, el) -> Position:
    p = _only(el)
    if p is None:
        raise ctx.error(el, "empty Position")
    t, w = _tag(p), ctx.where(p)
    o = _kid(p, "Orientation")
    h = _num(ctx, o, "h", 0.0) if o is not None else None
    if t == "WorldPosition":
        return Position("world", _num(ctx, p, "x"), _num(ctx, p, "y"), _num(ctx, p, "z", 0.0),
                        _num(ctx, p, "h") if p.get("h") is not None else None, where=w)
    if t == "LanePosition":
        return Position("lane", road_id=p.get("roadId", ""), lane_id=_int(ctx, p, "laneId"),
                        s=_num(ctx, p, "s"), offset=_num(ctx, p, "offset", 0.0), h=h, where=w)
    if t == "RelativeLanePosition":
        return Position("relative_lane", entity=p.get("entityRef", ""), d_lane=_int(ctx, p, "dLane"),
                        ds=_num(ctx, p, "ds", 0.0), offset=_num(ctx, p, "offset", 0.0), h=h, where=w)
    if t == "RelativeObjectPosition":
        return Position("relative_object", entity=p.get("entityRef", ""), dx=_num(ctx, p, "dx"),
                        dy=_num(ctx, p, "dy"), h=h, where=w)
    if t == "RelativeWorldPosition":
        return Position("relative_world", entity=p.get("entityRef", ""), dx=_num(ctx, p, "dx"),
                        dy=_num(ctx, p, "dy"), h=h, where=w)
    ctx.unsupported_el(p)
    return Position("unsupported", where=w)


def _dynamics(ctx, el) -> Dynamics:
    shape = el.get("dynamicsShape", "step")
    if shape not in ("step", "linear", "cubic", "sinusoidal"):
        ctx.unsupported_el(el, f"TransitionDynamics dynamicsShape={shape}")
        shape = "linear"
    dim = el.get("dynamicsDimension", "time")
    if dim not in ("time", "distance", "rate"):
        raise ctx.error(el, f"dynamicsDimension {dim!r}: time, distance or rate")
    v = _num(ctx, el, "value", 0.0)
    if v < 0:
        raise ctx.error(el, f"value {v} must be >= 0")
    return Dynamics(shape, dim, v)


def _private_action(ctx: _Ctx, el):
    """One action of a PrivateAction element (or Unsupported)."""
    a = _only(el)
    if a is None:
        raise ctx.error(el, "empty PrivateAction")
    w = ctx.where(a)
    t = _tag(a)
    if t == "TeleportAction":
        return TeleportAction(read_position(ctx, _kid(a, "Position")), w)
    if t == "RoutingAction":
        r = _only(a)
        if r is not None and _tag(r) == "AssignRouteAction":
            route = _kid(r, "Route")
            if route is None:
                return ctx.unsupported_el(r, "AssignRouteAction without an inline Route")
            return AssignRouteAction([read_position(ctx, _kid(wp, "Position"))
                                      for wp in _kids(route, "Waypoint")], route.get("name", ""), w)
        if r is not None and _tag(r) == "FollowTrajectoryAction":
            return _trajectory(ctx, r)
        return ctx.unsupported_el(r if r is not None else a)
    if t == "LongitudinalAction":
        s = _only(a)
        if s is not None and _tag(s) == "SpeedAction":
            dyn = _dynamics(ctx, _kid(s, "SpeedActionDynamics"))
            tgt = _only(_kid(s, "SpeedActionTarget"))
            if _tag(tgt) == "AbsoluteTargetSpeed":
                return SpeedAction(dyn, speed=_num(ctx, tgt, "value"), where=w)
            if tgt.get("continuous", "false") == "true":
                ctx.unsupported_el(tgt, "RelativeTargetSpeed continuous=true (applied once)")
            return SpeedAction(dyn, ref_entity=tgt.get("entityRef", ""), rel_value=_num(ctx, tgt, "value"),
                               rel_type=tgt.get("speedTargetValueType", "delta"), where=w)
        return ctx.unsupported_el(s if s is not None else a)
    if t == "LateralAction":
        s = _only(a)
        if s is not None and _tag(s) == "LaneChangeAction":
            dyn = _dynamics(ctx, _kid(s, "LaneChangeActionDynamics"))
            tgt = _only(_kid(s, "LaneChangeTarget"))
            off = _num(ctx, s, "targetLaneOffset", 0.0)
            if _tag(tgt) == "AbsoluteTargetLane":
                return LaneChangeAction(dyn, lane_id=_int(ctx, tgt, "value"), target_offset=off, where=w)
            return LaneChangeAction(dyn, ref_entity=tgt.get("entityRef", ""),
                                    rel_lanes=_int(ctx, tgt, "value"), target_offset=off, where=w)
        return ctx.unsupported_el(s if s is not None else a)
    if t == "SynchronizeAction":
        fs = _kid(a, "FinalSpeed")
        final = None
        if fs is not None and _kid(fs, "AbsoluteSpeed") is not None:
            final = _num(ctx, _kid(fs, "AbsoluteSpeed"), "value")
        elif fs is not None:
            ctx.unsupported_el(fs, "FinalSpeed RelativeSpeedToMaster")
        return SynchronizeAction(a.get("masterEntityRef", ""),
                                 read_position(ctx, _kid(a, "TargetPositionMaster")),
                                 read_position(ctx, _kid(a, "TargetPosition")), final, w)
    if t == "ActivateControllerAction":
        return Unsupported("ActivateControllerAction", w)   # the default controller plays on
    return ctx.unsupported_el(a)


def _trajectory(ctx: _Ctx, el) -> FollowTrajectoryAction:
    traj = _kid(el, "Trajectory")
    if traj is None:
        tr = _kid(el, "TrajectoryRef")
        traj = _kid(tr, "Trajectory") if tr is not None else None
    if traj is None:
        raise ctx.error(el, "no Trajectory")
    shape = _only(_kid(traj, "Shape"))
    if shape is None or _tag(shape) != "Polyline":
        ctx.unsupported_el(shape if shape is not None else traj,
                           f"Trajectory Shape {_tag(shape) if shape is not None else '(none)'}")
        return FollowTrajectoryAction([], where=ctx.where(el))
    verts = _kids(shape, "Vertex")
    if len(verts) > MAX_TRAJECTORY_VERTICES:
        raise ctx.error(shape, f"{len(verts)} vertices, more than {MAX_TRAJECTORY_VERTICES}")
    if len(verts) < 2:
        raise ctx.error(shape, "a polyline needs 2 vertices or more")
    vs = [(_num(ctx, v, "time") if v.get("time") is not None else None,
           read_position(ctx, _kid(v, "Position"))) for v in verts]
    timing = None
    tr = _kid(el, "TimeReference")
    tm = _kid(tr, "Timing") if tr is not None else None
    if tm is not None:
        timing = (tm.get("domainAbsoluteRelative", "absolute"), _num(ctx, tm, "scale", 1.0),
                  _num(ctx, tm, "offset", 0.0))
    return FollowTrajectoryAction(vs, traj.get("closed", "false") == "true", timing,
                                  traj.get("name", ""), ctx.where(el))


RULES = ("greaterThan", "lessThan", "equalTo", "greaterOrEqual", "lessOrEqual", "notEqualTo")
BY_ENTITY = ("TimeHeadwayCondition", "TimeToCollisionCondition", "ReachPositionCondition",
             "RelativeDistanceCondition", "TraveledDistanceCondition", "SpeedCondition",
             "RelativeSpeedCondition", "DistanceCondition", "StandStillCondition")
BY_VALUE = ("SimulationTimeCondition", "StoryboardElementStateCondition", "ParameterCondition")


def _condition(ctx: _Ctx, el) -> Condition:
    name = el.get("name", "")
    delay = _num(ctx, el, "delay", 0.0)
    if delay < 0:
        raise ctx.error(el, f"delay {delay} must be >= 0")
    edge = el.get("conditionEdge", "none")
    if edge not in ("rising", "falling", "risingOrFalling", "none"):
        raise ctx.error(el, f"conditionEdge {edge!r}: rising, falling, risingOrFalling or none")
    body = _only(el)
    ents, rule = [], "any"
    if body is not None and _tag(body) == "ByEntityCondition":
        te = _kid(body, "TriggeringEntities")
        rule = te.get("triggeringEntitiesRule", "any") if te is not None else "any"
        ents = [r.get("entityRef", "") for r in (_kids(te, "EntityRef") if te is not None else [])]
        c = _only(_kid(body, "EntityCondition"))
    elif body is not None and _tag(body) == "ByValueCondition":
        c = _only(body)
    else:
        raise ctx.error(el, "a Condition holds ByEntityCondition or ByValueCondition")
    kind = _tag(c)
    params = {k: v for k, v in c.attrib.items() if k != SRC_ATTR}
    if kind not in BY_ENTITY + BY_VALUE:
        ctx.unsupported_el(c)
        kind = "Unsupported:" + kind
    for k in ("value", "tolerance"):
        if k in params:
            params[k] = _num(ctx, c, k)
    if "rule" in params and params["rule"] not in RULES:
        raise ctx.error(c, f"rule {params['rule']!r}: one of {', '.join(RULES)}")
    pos = _kid(c, "Position")
    if pos is not None:
        params["position"] = read_position(ctx, pos)
    tgt = _kid(c, "TimeToCollisionConditionTarget")
    if tgt is not None:
        t = _only(tgt)
        if _tag(t) == "EntityRef":
            params["entityRef"] = t.get("entityRef", "")
        else:
            params["position"] = read_position(ctx, t)
    return Condition(name, kind, delay, edge, params, ents, rule, ctx.where(c))


def _trigger(ctx: _Ctx, el) -> Trigger | None:
    if el is None:
        return None
    groups = [[_condition(ctx, c) for c in _kids(g, "Condition")] for g in _kids(el, "ConditionGroup")]
    return Trigger([g for g in groups if g])


def _count(ctx, el) -> int:
    n = _int(ctx, el, "maximumExecutionCount", 1)
    if n < 1:
        raise ctx.error(el, f"maximumExecutionCount {n} must be >= 1")
    return n


def _entity(ctx: _Ctx, so) -> Entity:
    name = so.get("name", "")
    obj = next((c for c in so if isinstance(c.tag, str) and _tag(c) in ("Vehicle", "Pedestrian")), None)
    if obj is None:
        other = _only(so)
        ctx.unsupported_el(other if other is not None else so,
                           f"{_tag(other) if other is not None else 'ScenarioObject'} entity")
        return Entity(name, "vehicle", where=ctx.where(so))
    bb = _kid(obj, "BoundingBox")
    if _tag(obj) == "Vehicle":
        e = Entity(name, "vehicle", obj.get("vehicleCategory", "car"), where=ctx.where(obj))
    else:
        e = Entity(name, "pedestrian", obj.get("pedestrianCategory", "pedestrian"), 0.5, 0.6, 1.8,
                   (0.0, 0.0, 0.9), where=ctx.where(obj))
    if bb is not None:
        c, d = _kid(bb, "Center"), _kid(bb, "Dimensions")
        if d is not None:
            e.length, e.width, e.height = (_num(ctx, d, k) for k in ("length", "width", "height"))
            if min(e.length, e.width, e.height) <= 0 or max(e.length, e.width, e.height) > 100:
                raise ctx.error(d, "bounding box dimensions must be within (0, 100] m")
        if c is not None:
            e.center = tuple(_num(ctx, c, k) for k in ("x", "y", "z"))
    return e


def read_scenario(path: str | Path, ego: str | None = None) -> Scenario:
    """Read an OpenSCENARIO file (see the module doc); ``ego``: the entity the ego is
    (default the first ScenarioObject)."""
    path = Path(path)
    ctx = _Ctx(path)
    root = parse_file(path)
    if _tag(root) != "OpenSCENARIO":
        raise InputError(f"{path}:{root.sourceline}: root element <{_tag(root)}>, expected <OpenSCENARIO>")
    fh = _kid(root, "FileHeader")
    version = f"{fh.get('revMajor', '1')}.{fh.get('revMinor', '0')}" if fh is not None else "1.0"
    if _kid(root, "Storyboard") is None:
        raise InputError(f"{path}: no <Storyboard> (a catalog or a parameter distribution is not "
                         "a scenario)")
    _resolve_params(ctx, root, {})
    scope = {}
    decl = _kid(root, "ParameterDeclarations")
    for d in (_kids(decl, "ParameterDeclaration") if decl is not None else []):
        scope[d.get("name")] = d.get("value", "")
    _resolve_catalogs(ctx, root, scope)

    road_file = None
    rn = _kid(root, "RoadNetwork")
    lf = _kid(rn, "LogicFile") if rn is not None else None
    if lf is not None and lf.get("filepath"):
        road_file = ctx.inside(lf, lf.get("filepath"), "OpenDRIVE file")
        if not road_file.is_file():
            raise ctx.error(lf, f"OpenDRIVE file {lf.get('filepath')!r} not found ({road_file})")

    entities = {}
    ents = _kid(root, "Entities")
    for so in (_kids(ents, "ScenarioObject") if ents is not None else []):
        e = _entity(ctx, so)
        entities[e.name] = e
    for es in (_kids(ents, "EntitySelection") if ents is not None else []):
        ctx.unsupported_el(es)

    sb = _kid(root, "Storyboard")
    init: dict[str, list] = {n: [] for n in entities}
    ia = _kid(_kid(sb, "Init"), "Actions") if _kid(sb, "Init") is not None else None
    for c in (ia if ia is not None else []):
        if not isinstance(c.tag, str):
            continue
        if _tag(c) == "Private":
            ent = c.get("entityRef", "")
            if ent not in entities:
                raise ctx.error(c, f"entityRef {ent!r} names no entity")
            init[ent] += [_private_action(ctx, pa) for pa in _kids(c, "PrivateAction")]
        else:
            ctx.unsupported_el(c, f"Init {_tag(c)}")
    stories = []
    for st in _kids(sb, "Story"):
        acts = []
        for act in _kids(st, "Act"):
            groups = []
            for mg in _kids(act, "ManeuverGroup"):
                ac = _kid(mg, "Actors")
                actors = [r.get("entityRef", "") for r in (_kids(ac, "EntityRef") if ac is not None else [])]
                for a in actors:
                    if a not in entities:
                        raise ctx.error(ac, f"entityRef {a!r} names no entity")
                mans = []
                for man in _kids(mg, "Maneuver"):
                    evs = []
                    for ev in _kids(man, "Event"):
                        acts_ = []
                        for a in _kids(ev, "Action"):
                            pa = _kid(a, "PrivateAction")
                            if pa is not None:
                                acts_.append(PrivateAction(a.get("name", ""), _private_action(ctx, pa)))
                            else:
                                acts_.append(PrivateAction(a.get("name", ""), ctx.unsupported_el(
                                    _only(a) if _only(a) is not None else a)))
                        evs.append(Event(ev.get("name", ""), ev.get("priority", "parallel"), _count(ctx, ev),
                                         acts_, _trigger(ctx, _kid(ev, "StartTrigger")), ctx.where(ev)))
                    mans.append(Maneuver(man.get("name", ""), evs))
                groups.append(ManeuverGroup(mg.get("name", ""), _count(ctx, mg), actors, mans))
            acts.append(Act(act.get("name", ""), groups, _trigger(ctx, _kid(act, "StartTrigger")),
                            _trigger(ctx, _kid(act, "StopTrigger"))))
        stories.append(Story(st.get("name", ""), acts))
    params = dict(scope)
    sc = Scenario(path, version, road_file, entities, init, stories,
                  _trigger(ctx, _kid(sb, "StopTrigger")), params, ctx.unsupported)
    sc.choose_ego(ego)
    return sc
