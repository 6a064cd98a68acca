"""Measurement plans: which (theta_i, phi_i, theta_o, phi_o) to visit, as data.

A plan is a preset (``quick``, ``standard``, ``dense``: ``bench/presets/*.toml``), a CSV file
(header ``theta_i,phi_i,theta_o,phi_o``) or a TOML file (``name``, ``description``, optional
``points = [[30, 0, 40, 180], ...]``, any number of scans). Angles are degrees, theta in
[0, 90), phi wrapped to [-180, 180); ``phi_i = 0, phi_o = 180`` is the specular side::

    [[scan]]
    kind = "in_plane"                     # in_plane | hemisphere | isotropic | points
    theta_i = [15, 45]
    theta_o = [-70, -50, 50, 70]          # signed: < 0 on the incidence side (phi_o = 0)
    reciprocal = true                     # also measure each point's reciprocal partner

Plans are validated on load (`PlanError`: one line); `check_plan` lists what the bench cannot
reach. ``[spectral]`` (`gonio.bench.plan.spectral`): every geometry at every wavelength.
"""

# Generators `in_plane`, `hemisphere_grid`, `isotropic_grid`, `with_reciprocal`; `thin` keeps every
# k-th point of a plan (the sequential plans' peer in `gonio perf acquisition`). A spectral plan:
# ``[spectral] from_nm, to_nm, step_nm``, the ``spectral`` preset or ``spectral:STEP``.

# phi may be any finite value (wrapped); phi_i = 0, phi_o = 180 is the specular side of the
# plane of incidence. CSV plans hold one point per row. Generators:
# hemisphere_grid puts directions uniform in solid angle, on equal-area rings; isotropic_grid
# spans (theta_i, theta_o, phi_d); with_reciprocal adds swapped partners. check_plan runs
# before anything moves.

from __future__ import annotations

import csv
import io
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from gonio.core.preflight import check_input_file
from gonio.core.sides import REFLECTION_ONLY, Side, parse_sides
from gonio.core.tomlfile import MAX_BYTES, parse_toml
from gonio.bench.plan import kinematics
from gonio.bench.plan.markers import roi_masks_fast
from gonio.bench.plan.ordering import order_moves
from gonio.core.errors import GonioError, PlanError, UnreachableError

__all__ = [
    "Plan",
    "PRESETS",
    "preset_names",
    "load_plan",
    "plan_from_dict",
    "in_plane",
    "hemisphere_grid",
    "isotropic_grid",
    "with_reciprocal",
    "thin",
    "find_partners",
    "check_plan",
    "require_reachable",
    "DryRun",
    "dry_run",
]

PRESET_DIR = Path(__file__).with_name("presets")
PRESETS = ("quick", "standard", "dense", "glossy", "transmission", "both-sides", "spectral")
COLUMNS = ("theta_i", "phi_i", "theta_o", "phi_o")
#: most points in one plan (the dense preset has about 1000): the ordering's N x N matrices
#: stay under 128 MiB each, and a generator never runs without bound
MAX_POINTS = 4000


def preset_names() -> list[str]:
    """Names of the plan presets shipped in ``bench/presets``."""
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


@dataclass
class Plan:
    """A validated measurement plan.

    Attributes
    ----------
    name : str
    angles : ndarray (N, 4)
        ``(theta_i, phi_i, theta_o, phi_o)`` per point, degrees; phi in [-180, 180).
    partner : ndarray of int (N,)
        Index of the point's reciprocal partner (wi and wo swapped), -1 if none.
    description : str
    source : str
        Where the plan came from (preset name or file path).
    duplicates : int
        Points given more than once and dropped (the first occurrence is kept), whatever the
        plan's format: a plan holds each point once.
    sides : tuple of Side
        The sides its points lie on (:mod:`gonio.core.sides`; reflection unless the plan
        file says ``sides``); every theta_o must lie on one of them.
    wavelength_nm : ndarray (N,), optional
        A spectral plan: the monochromator's wavelength at each point (nm); None otherwise.
    """

    name: str
    angles: np.ndarray
    partner: np.ndarray = field(default=None)
    description: str = ""
    source: str = ""
    duplicates: int = 0
    sides: tuple = REFLECTION_ONLY
    wavelength_nm: np.ndarray | None = None

    def __post_init__(self):
        a = _validated_angles(self.angles, self.name, self.sides)
        wl = None
        if self.wavelength_nm is not None:
            from gonio.bench.plan.spectral import checked_wavelengths

            wl = checked_wavelengths(self.wavelength_nm, self.name, len(a))
        a, dropped = dedupe(a if wl is None else np.column_stack([a, wl]))
        self.angles, self.wavelength_nm = (a, None) if wl is None else (a[:, :4].copy(), a[:, 4].copy())
        self.duplicates += dropped
        if self.partner is None or dropped:
            self.partner = find_partners(self.angles, wavelength_nm=self.wavelength_nm)

    def __len__(self) -> int:
        return int(self.angles.shape[0])

    def to_dict(self) -> dict[str, Any]:
        """A TOML-friendly dict (`plan_from_dict` reads it back to the same plan)."""
        d = {"name": self.name, "description": self.description, "source": self.source,
             "points": [[float(v) for v in row] for row in self.angles]}
        if self.sides != REFLECTION_ONLY:
            d["sides"] = [s.value for s in self.sides]
        if self.wavelength_nm is not None:
            d["wavelength_nm"] = [float(v) for v in self.wavelength_nm]
        return d


def _validated_angles(angles, name: str, sides=REFLECTION_ONLY) -> np.ndarray:
    try:
        a = np.array(angles, dtype=float)
    except (TypeError, ValueError):
        raise PlanError(f"plan {name!r}: points must be lists of 4 numbers "
                        "(theta_i, phi_i, theta_o, phi_o in degrees); fix the plan file") from None
    if a.size == 0:
        raise PlanError(f"plan {name!r} has no points; add points or scans to it")
    if a.ndim == 2 and a.shape[0] > MAX_POINTS:
        raise PlanError(f"plan {name!r} has {a.shape[0]} points, more than {MAX_POINTS} (the move ordering's "
                        f"N x N matrices would need {8 * a.shape[0] ** 2 / 2 ** 20:.0f} MiB each); split it into plans "
                        f"of at most {MAX_POINTS} points")
    if a.ndim != 2 or a.shape[1] != 4:
        raise PlanError(f"plan {name!r}: each point needs exactly 4 angles "
                        "(theta_i, phi_i, theta_o, phi_o in degrees); fix the plan file")
    bad = ~np.isfinite(a).all(1)
    if bad.any():
        k = int(np.argmax(bad))
        raise PlanError(f"plan {name!r}: point {k} has a non-finite angle {a[k].tolist()}; fix the plan file")
    bad = ~((a[:, 0] >= 0) & (a[:, 0] < 90))
    on_side = np.zeros(a.shape[0], dtype=bool)
    for s in sides:
        on_side |= s.holds_theta_o(a[:, 2])
    bad |= ~on_side
    if bad.any():
        k = int(np.argmax(bad))
        if tuple(sides) == REFLECTION_ONLY:
            raise PlanError(f"plan {name!r}: point {k} {a[k].tolist()} has theta outside [0, 90) deg; "
                            "fix the plan file")
        ranges = " or ".join("[0, 90)" if s is Side.REFLECT else "(90, 180]" for s in sides)
        raise PlanError(f"plan {name!r}: point {k} {a[k].tolist()} has theta_i outside [0, 90) deg or theta_o "
                        f"outside {ranges} deg (sides: {', '.join(s.value for s in sides)}); fix the plan file")
    a[:, [1, 3]] = (a[:, [1, 3]] + 180.0) % 360.0 - 180.0
    return a


def dedupe(angles: np.ndarray) -> tuple[np.ndarray, int]:
    """``angles`` (validated, phi wrapped) without repeated points (first kept), and how many went."""
    _, first = np.unique(np.round(angles, 9), axis=0, return_index=True)
    if len(first) == len(angles):
        return angles, 0
    return angles[np.sort(first)], len(angles) - len(first)


def find_partners(angles, tol_deg: float = 1e-6, wavelength_nm=None) -> np.ndarray:
    """Index of each point's reciprocal partner (wi and wo swapped, same azimuths; at the same
    wavelength in a spectral plan), -1 if none."""
    a = np.asarray(angles, float)
    wl = np.zeros(len(a)) if wavelength_nm is None else np.asarray(wavelength_nm, float)
    key = lambda row, w: (*np.round(np.asarray(row) / tol_deg).astype(np.int64), round(float(w) * 1e6))
    index = {}
    for k, row in enumerate(a):
        index.setdefault(key(row, wl[k]), k)
    out = np.full(len(a), -1, int)
    for k, (ti, pi_, to, po) in enumerate(a):
        if abs(ti - to) < tol_deg and abs(((pi_ - po + 180) % 360) - 180) < tol_deg:
            continue                      # its own partner: nothing to compare
        j = index.get(key((to, po, ti, pi_), wl[k]))
        if j is not None and j != k:
            out[k] = j
    return out


# -- generators ---------------------------------------------------------------------------------

def in_plane(theta_i: Iterable[float], theta_o: Iterable[float], phi: float = 0.0,
             exclude_backscatter_deg: float = 8.0) -> np.ndarray:
    """In-plane scans: for each theta_i, every signed theta_o (degrees).

    ``theta_o > 0`` lies on the specular side (``phi_o = phi + 180``), ``theta_o < 0`` on the
    incidence side (``phi_o = phi``). Points with wo within ``exclude_backscatter_deg`` of wi
    (the lamp would block the camera) are left out.
    """
    rows = []
    for ti in theta_i:
        for to in theta_o:
            if to < 0 and abs(-to - ti) < exclude_backscatter_deg:
                continue
            rows.append((ti, phi, abs(to), phi + 180.0 if to >= 0 else phi))
    return np.array(rows, float).reshape(-1, 4)


def hemisphere_directions(n: int, max_theta_deg: float = 80.0) -> tuple[np.ndarray, np.ndarray]:
    """About ``n`` directions uniform in solid angle over the cap theta <= max_theta (degrees).

    Equal-width rings in theta, each holding a number of directions proportional to its solid
    angle, at the ring's solid-angle midpoint, azimuths staggered from ring to ring.

    Returns
    -------
    theta, phi : ndarray
        Degrees.
    """
    if n < 1:
        raise PlanError("a hemisphere scan needs n >= 1; fix the plan file")
    if n > MAX_POINTS:
        raise PlanError(f"a hemisphere scan of n = {n} directions is more than a plan holds ({MAX_POINTS}); "
                        "lower n in the plan file")
    if not 0 < max_theta_deg < 90:
        raise PlanError(f"hemisphere max_theta {max_theta_deg} must be in (0, 90) deg; fix the plan file")
    tmax = math.radians(max_theta_deg)
    omega = 2 * math.pi * (1 - math.cos(tmax))
    cell = omega / n
    rings = max(1, round(tmax / math.sqrt(cell)))
    edges = np.linspace(0.0, tmax, rings + 1)
    theta, phi = [], []
    for r in range(rings):
        c0, c1 = math.cos(edges[r]), math.cos(edges[r + 1])
        m = max(1, round(2 * math.pi * (c0 - c1) / cell))
        t = math.degrees(math.acos(0.5 * (c0 + c1)))
        for j in range(m):
            theta.append(t)
            phi.append((j + 0.5 * (r % 2)) * 360.0 / m)
    return np.array(theta), (np.array(phi) + 180.0) % 360.0 - 180.0


def hemisphere_grid(theta_i: Iterable[float], n: int, max_theta_deg: float = 80.0,
                    exclude_backscatter_deg: float = 8.0) -> np.ndarray:
    """For each theta_i (phi_i = 0), about ``n`` outgoing directions uniform in solid angle."""
    to, po = hemisphere_directions(n, max_theta_deg)
    wo = kinematics.directions(to, po)
    rows = []
    for ti in theta_i:
        wi = kinematics.directions(ti, 0.0)
        keep = np.degrees(np.arccos(np.clip(wo @ wi, -1, 1))) >= exclude_backscatter_deg
        rows += [(ti, 0.0, a, b) for a, b in zip(to[keep], po[keep])]
    return np.array(rows, float).reshape(-1, 4)


def isotropic_grid(theta_i: Iterable[float], theta_o: Iterable[float], phi_d: Iterable[float],
                   exclude_backscatter_deg: float = 8.0) -> np.ndarray:
    """The 3-D grid of an isotropic BRDF: phi_i = 0, phi_o = phi_d (180: specular plane)."""
    rows = []
    for ti in theta_i:
        for to in theta_o:
            for pd in phi_d:
                wi = kinematics.directions(ti, 0.0)
                wo = kinematics.directions(to, pd)
                if math.degrees(math.acos(min(1.0, float(wi @ wo)))) >= exclude_backscatter_deg:
                    rows.append((ti, 0.0, to, pd))
    return np.array(rows, float).reshape(-1, 4)


def with_reciprocal(angles) -> np.ndarray:
    """``angles`` followed by each point's reciprocal partner (wi and wo swapped) not yet in it."""
    a = np.asarray(angles, float).reshape(-1, 4)
    swapped = a[:, [2, 3, 0, 1]]
    out = [*a]
    have = {tuple(np.round(r, 6)) for r in a}
    for r in swapped:
        k = tuple(np.round(r, 6))
        if k not in have:
            have.add(k)
            out.append(r)
    return np.array(out, float).reshape(-1, 4)


def thin(plan: Plan, stride: int, offset: int = 0) -> Plan:
    """Every ``stride``-th point of ``plan`` as listed, from its ``offset``-th: a uniform thinning
    that keeps the plan's mix of scans (each scan's share of the points), for a plan of the same
    kind at about 1/``stride`` of the points. A stride that divides a scan's length per incidence
    (dense: 120 directions each) takes the same directions at every incidence of that scan.
    ValueError (one line) for a stride that is not a whole number >= 1 or an offset outside
    [0, stride)."""
    for name, v in (("stride", stride), ("offset", offset)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise ValueError(f"thin: {name} = {str(v)[:40]!r}: give a whole number")
    if not 1 <= stride <= len(plan):
        raise ValueError(f"thin: stride {stride}: give 1 to {len(plan)} (the plan's points)")
    if not 0 <= offset < stride:
        raise ValueError(f"thin: offset {offset}: give 0 to {stride - 1}")
    if plan.wavelength_nm is not None:
        raise ValueError(f"thin: plan {plan.name!r} is spectral; thin its geometries before the wavelengths")
    return Plan(f"{plan.name}-thinned-{stride}", plan.angles[offset::stride].copy(),
                description=f"every {stride}th point of {plan.name} from point {offset}",
                source=f"{plan.source or plan.name}, thinned 1/{stride} from {offset}", sides=plan.sides)


_SCAN_KEYS = {
    "in_plane": {"theta_i", "theta_o", "phi", "exclude_backscatter_deg"},
    "hemisphere": {"theta_i", "n", "max_theta", "exclude_backscatter_deg"},
    "isotropic": {"theta_i", "theta_o", "phi_d", "exclude_backscatter_deg"},
    "points": {"points"},
}


def _scan(spec: Mapping[str, Any], name: str, k: int) -> np.ndarray:
    spec = dict(spec)
    kind = spec.pop("kind", None)
    reciprocal = spec.pop("reciprocal", False)
    if kind not in _SCAN_KEYS:
        raise PlanError(f"plan {name!r}: scan {k} has kind {kind!r}; use one of {', '.join(_SCAN_KEYS)}")
    extra = set(spec) - _SCAN_KEYS[kind]
    if extra:
        raise PlanError(f"plan {name!r}: scan {k} ({kind}) has unknown keys {sorted(extra)}; "
                        f"allowed: {sorted(_SCAN_KEYS[kind])}")
    try:
        lengths = {key: (len(v) if isinstance(v, list) else 1) for key, v in spec.items()
                   if key in ("theta_i", "theta_o", "phi_d")}
        count = math.prod(lengths.values()) * (int(spec["n"]) if kind == "hemisphere" else 1)
        if count > MAX_POINTS:
            raise PlanError(f"plan {name!r}: scan {k} ({kind}) makes about {count} points, more than a plan holds "
                            f"({MAX_POINTS}); make it smaller")
        if kind == "in_plane":
            a = in_plane(_nums(spec["theta_i"]), _nums(spec["theta_o"]), float(spec.get("phi", 0.0)),
                         float(spec.get("exclude_backscatter_deg", 8.0)))
        elif kind == "hemisphere":
            a = hemisphere_grid(_nums(spec["theta_i"]), int(spec["n"]), float(spec.get("max_theta", 80.0)),
                                float(spec.get("exclude_backscatter_deg", 8.0)))
        elif kind == "isotropic":
            a = isotropic_grid(_nums(spec["theta_i"]), _nums(spec["theta_o"]), _nums(spec["phi_d"]),
                               float(spec.get("exclude_backscatter_deg", 8.0)))
        else:
            a = _validated_angles(spec["points"], name, tuple(Side))   # the plan's sides are checked on the whole
    except KeyError as exc:
        raise PlanError(f"plan {name!r}: scan {k} ({kind}) lacks {exc}; add it") from None
    except (TypeError, ValueError):
        raise PlanError(f"plan {name!r}: scan {k} ({kind}) has a value that is not a number "
                        "or a list of numbers; fix the plan file") from None
    return with_reciprocal(a) if reciprocal else a


def _nums(v) -> list[float]:
    v = [v] if isinstance(v, (int, float)) else list(v)
    out = [float(x) for x in v]
    if not all(math.isfinite(x) for x in out):
        raise ValueError("non-finite")
    return out


def plan_from_dict(d: Mapping[str, Any], default_name: str = "plan", source: str = "") -> Plan:
    """Build a `Plan` from a parsed TOML document (see the module docstring)."""
    name = str(d.get("name", default_name))
    unknown = set(d) - {"name", "description", "points", "scan", "source", "sides", "spectral", "wavelength_nm"}
    if unknown:
        raise PlanError(f"plan {name!r} has unknown keys {sorted(unknown)}; allowed: name, description, "
                        "sides, points, [[scan]], [spectral]")
    try:
        sides = parse_sides(d.get("sides", "reflect"), f"plan {name!r}")
    except ValueError as exc:
        raise PlanError(f"{exc}; fix the plan file") from None
    parts = []
    if "points" in d:
        parts.append(_validated_angles(d["points"], name, sides))
    scans = d.get("scan", [])
    if not isinstance(scans, list):
        raise PlanError(f"plan {name!r}: 'scan' must be an array of tables ([[scan]]); fix the plan file")
    for k, spec in enumerate(scans):
        if not isinstance(spec, Mapping):
            raise PlanError(f"plan {name!r}: scan {k} is not a table; fix the plan file")
        parts.append(_scan(spec, name, k))
    if not parts:
        raise PlanError(f"plan {name!r} has no points; add 'points' or [[scan]] tables")
    angles = _validated_angles(np.vstack(parts), name, sides)     # Plan drops repeated points, keeping the first
    wl = d.get("wavelength_nm")                                     # a spectral plan as to_dict wrote it
    if "spectral" in d:                                             # every geometry at every wavelength
        from gonio.bench.plan.spectral import expand, grid

        if wl is not None:
            raise PlanError(f"plan {name!r} has both [spectral] and wavelength_nm; give one of them")
        angles, wl = expand(dedupe(angles)[0], grid(d["spectral"], name))
    return Plan(name, angles, description=str(d.get("description", "")), source=source or str(d.get("source", "")),
                sides=sides, wavelength_nm=wl)


def load_plan(spec: str | Path) -> Plan:
    """Load a plan from a preset name, a ``.toml`` or a ``.csv`` file.

    Raises
    ------
    PlanError
        Unknown preset, missing file, malformed TOML/CSV, invalid angles.
    """
    spec_s = str(spec)
    if spec_s.startswith("spectral:") and "spectral" in preset_names():      # the preset at another step
        from gonio.bench.plan.spectral import with_step

        doc = tomllib.loads((PRESET_DIR / "spectral.toml").read_text())
        return plan_from_dict(with_step(doc, spec_s.partition(":")[2]), "spectral", source=f"preset:{spec_s}")
    if spec_s in preset_names():
        path = PRESET_DIR / f"{spec_s}.toml"
        return plan_from_dict(tomllib.loads(path.read_text()), spec_s, source=f"preset:{spec_s}")
    path = Path(spec_s)
    if path.suffix.lower() not in (".toml", ".csv"):
        if not path.exists():
            raise PlanError(f"unknown plan {spec_s!r}: use a preset ({', '.join(preset_names())}) "
                            "or a .toml/.csv plan file")
    if path.exists() and not path.is_dir():
        try:
            check_input_file(path, "plan file", max_bytes=MAX_BYTES)   # a FIFO or device would block
        except GonioError as exc:
            raise PlanError(str(exc)) from None
    try:
        text = path.read_text()
    except OSError as exc:
        raise PlanError(f"cannot read plan file {path}: {exc.strerror or exc}; check the path "
                        f"or use a preset ({', '.join(preset_names())})") from None
    except UnicodeDecodeError:
        raise PlanError(f"plan file {path} is not UTF-8 text; give a plan TOML or CSV file") from None
    if path.suffix.lower() == ".csv":
        return _plan_from_csv(text, path)
    try:
        doc = parse_toml(text, f"plan file {path}")
    except GonioError as exc:
        raise PlanError(str(exc)) from None
    return plan_from_dict(doc, path.stem, source=str(path))


def _plan_from_csv(text: str, path: Path) -> Plan:
    rows = [r for r in csv.reader(io.StringIO(text)) if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise PlanError(f"plan file {path} is empty; add a header theta_i,phi_i,theta_o,phi_o and rows")
    header = [h.strip() for h in rows[0]]
    if header != list(COLUMNS):
        raise PlanError(f"plan file {path}: header must be {','.join(COLUMNS)}, not {','.join(header)}")
    try:
        pts = [[float(x) for x in r] for r in rows[1:]]
    except ValueError:
        raise PlanError(f"plan file {path} has a value that is not a number; fix the file") from None
    return Plan(path.stem, pts, source=str(path))


# -- reachability and the dry run ------------------------------------------------------------

def check_plan(plan: Plan, settings: Mapping) -> list[tuple[int, tuple[float, ...], str]]:
    """Points the instrument cannot reach: ``[(index, (theta_i, phi_i, theta_o, phi_o), reason), ...]``.

    The regions in view are the capture's own (``_markers.roi_masks_fast``): with the exact
    corner test of ``kinematics.roi_masks`` a 6000 x 4000 camera's check took 2.1 s of CPU a
    point, 37 minutes for the ``standard`` plan before the first move."""
    r = kinematics.reachable(*plan.angles.T, settings, masks=roi_masks_fast, sides=plan.sides)
    return [(k, tuple(float(v) for v in plan.angles[k]), r.reason[k]) for k in np.flatnonzero(~r.ok)]


def require_reachable(plan: Plan, settings: Mapping) -> np.ndarray:
    """Stage poses (N, 4) degrees of every point; `UnreachableError` naming the first bad ones otherwise."""
    bad = check_plan(plan, settings)
    if bad:
        shown = "; ".join(f"point {k} {tuple(round(v, 2) for v in a)}: {why}" for k, a, why in bad[:3])
        more = f" and {len(bad) - 3} more" if len(bad) > 3 else ""
        raise UnreachableError(f"plan {plan.name!r} has {len(bad)} unreachable point(s): {shown}{more}; "
                               "remove them from the plan (a dry run lists all)")
    return kinematics.inverse(*plan.angles.T)


@dataclass(frozen=True)
class DryRun:
    """What a capture of a plan would do, computed without touching the instrument.

    Attributes
    ----------
    n_points : int
    unreachable : list
        As `check_plan`.
    naive_move_s, ordered_move_s, bound_move_s : float
        Stage travel time in plan order, after ordering, and its lower bound, s.
    per_point_s : float
        Assumed time per point for settling, exposures and read-out, s.
    order : ndarray of int
        The visiting order (empty if some point is unreachable).
    """

    n_points: int
    unreachable: list
    naive_move_s: float
    ordered_move_s: float
    bound_move_s: float
    per_point_s: float
    order: np.ndarray
    duplicates: int = 0
    monochromator_s: float = 0.0       # a spectral plan: the monochromator's moves in the chosen order
    spectral: str = ""                 # a spectral plan: the wavelength axis chosen, both estimates

    @property
    def estimated_s(self) -> float:
        """Estimated duration of the capture, s."""
        return self.ordered_move_s + self.monochromator_s + self.n_points * self.per_point_s

    def summary(self) -> str:
        """Human-readable lines for the CLI."""
        lines = [f"{self.n_points} points; estimated duration {self.estimated_s / 60:.1f} min "
                 f"(moves {self.ordered_move_s:.0f} s + {self.per_point_s:g} s per point)"]
        if self.spectral:
            lines.append(self.spectral)
        if self.duplicates:
            lines.append(f"{self.duplicates} repeated point(s) in the plan dropped (each point is measured once)")
        if self.naive_move_s > 0:
            lines.append(f"move time: plan order {self.naive_move_s:.0f} s, ordered {self.ordered_move_s:.0f} s "
                         f"({100 * (1 - self.ordered_move_s / self.naive_move_s):.0f} % less), "
                         f"lower bound {self.bound_move_s:.0f} s")
        if self.unreachable:
            lines.append(f"{len(self.unreachable)} unreachable point(s):")
            lines += [f"  point {k}: theta_i={a[0]:g} phi_i={a[1]:g} theta_o={a[2]:g} phi_o={a[3]:g} deg: {why}"
                      for k, a, why in self.unreachable]
        return "\n".join(lines)


def dry_run(plan: Plan, settings: Mapping, per_point_s: float = 2.0) -> DryRun:
    """Point count, move times (plan order, ordered, bound), estimated duration, unreachable points."""
    bad = check_plan(plan, settings)
    if bad:
        return DryRun(len(plan), bad, 0.0, 0.0, 0.0, per_point_s, np.zeros(0, int), plan.duplicates)
    stage = kinematics.inverse(*plan.angles.T)
    if plan.wavelength_nm is not None:
        from gonio.bench.plan.spectral import spectral_order

        res, why = spectral_order(plan.angles, plan.wavelength_nm, stage, settings)
        mono = why.fastest[1] if why.axis == "fastest" else why.slowest[1]
        return DryRun(len(plan), [], res.naive_s, res.ordered_s, res.bound_s, per_point_s, res.order, plan.duplicates,
                      mono, why.line())
    res = order_moves(stage, settings)
    return DryRun(len(plan), [], res.naive_s, res.ordered_s, res.bound_s, per_point_s, res.order, plan.duplicates)
