"""The pbr renderer's scene geometry, in numpy: the holder's top face with its rounded or
chamfered, chipped pocket edge (:func:`edge_radius`, :func:`surface_depth`), the pocket walls
and floor, the worn cutter, slurry lumps and the cutterhead plate as triangle meshes
(:func:`build_geometry`), the top face's textures (:func:`top_textures`), and the truth read
off that geometry: which corners are hidden (:func:`hidden_corners`) and the edge radius
along each edge (:func:`edge_radius_stats`). Convention: :mod:`cutterpose.render.pbr`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..geometry.holder import Holder
from ..geometry.pose import Pose
from .sensor import fractal_noise

__all__ = ["point_on_contour", "outward_normal", "inside_pocket", "orient_faces",
           "edge_radius", "surface_depth", "MeshData", "build_geometry", "top_textures",
           "hidden_corners", "edge_radius_stats"]


def point_on_contour(rng, corners: np.ndarray) -> tuple[int, float, np.ndarray]:
    """A point drawn uniformly along the contour: (edge index, fraction, point)."""
    d = np.roll(corners, -1, axis=0) - corners
    L = np.linalg.norm(d, axis=1)
    k = int(rng.choice(len(L), p=L / L.sum()))
    f = float(rng.uniform(0.0, 1.0))
    return k, f, corners[k] + f * d[k]


def outward_normal(corners: np.ndarray, k: int) -> np.ndarray:
    """Unit normal of edge ``k`` pointing out of the pocket (onto the top face)."""
    d = np.roll(corners, -1, axis=0)[k] - corners[k]
    return np.array([d[1], -d[0]]) / np.linalg.norm(d)


def inside_pocket(X, Y, corners) -> np.ndarray:
    """Even-odd test against the axis-parallel inner contour (half-open)."""
    X = np.asarray(X, float)
    Y = np.asarray(Y, float)
    inside = np.zeros(X.shape, bool)
    nxt = np.roll(corners, -1, axis=0)
    for (xa, ya), (xb, yb) in zip(corners, nxt):
        if xa != xb:
            continue
        lo, hi = min(ya, yb), max(ya, yb)
        inside ^= (Y >= lo) & (Y < hi) & (X < xa)
    return inside


def _dist_to_contour(X, Y, corners) -> np.ndarray:
    """Euclidean distance (mm) of points to the closed contour."""
    X = np.asarray(X, np.float64)
    Y = np.asarray(Y, np.float64)
    best = np.full(X.shape, np.inf)
    for p, q in zip(corners, np.roll(corners, -1, axis=0)):
        d = q - p
        t = np.clip(((X - p[0]) * d[0] + (Y - p[1]) * d[1]) / float(d @ d), 0.0, 1.0)
        best = np.minimum(best, np.hypot(X - p[0] - t * d[0], Y - p[1] - t * d[1]))
    return best


def edge_radius(params: dict, X, Y) -> np.ndarray:
    """Edge radius (or chamfer size) field in mm at holder points ``(X, Y)``."""
    lo, hi = params["radius_lo_mm"], params["radius_hi_mm"]
    X = np.asarray(X, np.float64)
    if hi <= 0:
        return np.zeros(X.shape)
    from scipy.special import ndtr

    w = params["radius_waves"]
    g = sum(a * np.cos(kx * X + ky * np.asarray(Y, float) + ph) for a, kx, ky, ph in w)
    g = g / math.sqrt(sum(a * a for a, *_ in w) / 2)
    return lo + (hi - lo) * ndtr(g)


def surface_depth(params: dict, holder: Holder, X, Y) -> np.ndarray:
    """Z (mm, >= 0) of the top surface at points ``(X, Y)`` off the pocket: 0 on the flat face,
    the fillet or chamfer near the contour, and the chips."""
    X = np.asarray(X, np.float64)
    Y = np.asarray(Y, np.float64)
    s = _dist_to_contour(X, Y, holder.corners_mm)
    r = edge_radius(params, X, Y)
    t = np.clip(r - s, 0.0, None)
    if params["profile"] == "chamfer":
        Z = t
    else:
        Z = r - np.sqrt(np.clip(r * r - t * t, 0.0, None))
    for ch in params["chips"]:
        k = ch["edge"]
        c = holder.corners_mm
        d = np.roll(c, -1, axis=0)[k] - c[k]
        e = d / np.linalg.norm(d)
        dx, dy = X - ch["x_mm"], Y - ch["y_mm"]
        ua = (dx * e[0] + dy * e[1]) / ch["half_length_mm"]
        ub = (-dx * e[1] + dy * e[0]) / ch["half_width_mm"]
        amp, ph = ch["wobble"]
        q2 = (ua * ua + ub * ub) * (1.0 + amp * np.cos(3.0 * np.arctan2(ub, ua) + ph))
        Z = np.maximum(Z, ch["depth_mm"] * np.sqrt(np.clip(1.0 - q2, 0.0, None)))
    return Z


def _grid_lines(lo: float, hi: float, keys, band: float, extra=(), coarse: float = 4.0,
                step_far: float = 0.2) -> np.ndarray:
    """Grid coordinates over [lo, hi]: coarse, plus lines crowding quadratically towards each
    contour coordinate in ``keys`` within ``band``, plus ``extra`` (fine ranges)."""
    parts = [np.arange(lo, hi, coarse), np.array([lo, hi], float), np.asarray(keys, float)]
    if band > 0:
        n = max(4, int(math.ceil(2.0 * band / step_far)))
        off = band * (np.arange(1, n + 1) / n) ** 2
        for k in keys:
            parts += [k - off, k + off]
    for c0, c1 in extra:
        parts.append(np.arange(c0, c1, step_far))
    x = np.unique(np.round(np.concatenate(parts), 6))
    return x[(x >= lo) & (x <= hi)]


def _vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals of a triangle mesh (float32)."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V, dtype=np.float64)
    for j in range(3):
        for c in range(3):
            N[:, c] += np.bincount(F[:, j], weights=fn[:, c], minlength=len(V))
    n = np.linalg.norm(N, axis=1, keepdims=True)
    n[n == 0] = 1.0
    return (N / n).astype(np.float32)


def orient_faces(V: np.ndarray, F: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Flip the triangles whose geometric normal points against ``want`` ((F,3) or (3,))."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    bad = np.einsum("ij,ij->i", fn, np.broadcast_to(want, fn.shape)) < 0
    F = F.copy()
    F[bad] = F[bad][:, [0, 2, 1]]
    return F


def _quad_faces(n_a: int, n_b: int) -> np.ndarray:
    """Triangles of an ``n_a x n_b`` vertex grid (row-major)."""
    i, j = np.meshgrid(np.arange(n_a - 1), np.arange(n_b - 1), indexing="ij")
    v0 = (i * n_b + j).ravel()
    v1, v2, v3 = v0 + 1, v0 + n_b, v0 + n_b + 1
    return np.concatenate([np.stack([v0, v2, v1], 1), np.stack([v1, v2, v3], 1)])


@dataclass
class MeshData:
    """A triangle mesh in numpy: vertices (V,3), faces (F,3), optional normals and uv."""

    name: str
    V: np.ndarray
    F: np.ndarray
    N: np.ndarray | None = None
    UV: np.ndarray | None = None


def _rect_mesh(name, x0, x1, y0, y1, z, normal_z=-1.0, uv_box=None) -> MeshData:
    """A rectangle in the plane ``Z = z``; ``uv_box = (X0, X1, Y0, Y1)`` maps uv onto it."""
    V = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float32)
    F = orient_faces(V, np.array([[0, 1, 2], [0, 2, 3]]), np.array([0, 0, normal_z]))
    uv = None
    if uv_box is not None:
        X0, X1, Y0, Y1 = uv_box
        uv = np.column_stack([(V[:, 0] - X0) / (X1 - X0), (V[:, 1] - Y0) / (Y1 - Y0)])
    return MeshData(name, V, F, None, None if uv is None else uv.astype(np.float32))


def _wall_mesh(name, P0, P1, z_top0, z_top1, z_bot, normal) -> MeshData:
    """A vertical quad from the segment ``P0 -> P1`` (tops at ``z_top``) down to ``z_bot``."""
    V = np.array([[P0[0], P0[1], z_top0], [P1[0], P1[1], z_top1], [P1[0], P1[1], z_bot],
                  [P0[0], P0[1], z_bot]], np.float32)
    F = orient_faces(V, np.array([[0, 1, 2], [0, 2, 3]]), np.array([normal[0], normal[1], 0.0]))
    return MeshData(name, V, F)


def _merge(name: str, parts: list[MeshData]) -> MeshData:
    Vs, Fs, off = [], [], 0
    for m in parts:
        Vs.append(m.V)
        Fs.append(m.F + off)
        off += len(m.V)
    uv = (np.concatenate([m.UV for m in parts]) if all(m.UV is not None for m in parts)
          else None)
    return MeshData(name, np.concatenate(Vs).astype(np.float32), np.concatenate(Fs), None, uv)


def _top_and_walls(params: dict, holder: Holder,
                   step_mm: float = 0.2) -> tuple[MeshData, MeshData, MeshData]:
    """The holder's top face (a height field on a grid crowded at the contour, ``step_mm``
    apart at the most), the pocket walls (sharing the face's boundary vertices) and the
    pocket floor."""
    c = holder.corners_mm
    a, b = holder.outer_length_x_mm / 2, holder.outer_width_y_mm / 2
    band = params["radius_hi_mm"]
    ex, ey = [], []
    for ch in params["chips"]:
        band = max(band, 1.3 * ch["half_width_mm"])
        ext = ch["half_length_mm"] * 1.3 + 0.5
        if holder.edge_direction_index[ch["edge"]] == 0:  # edge along X
            ex.append((ch["x_mm"] - ext, ch["x_mm"] + ext))
        else:
            ey.append((ch["y_mm"] - ext, ch["y_mm"] + ext))
    band = band + 1.0 if band > 0 else 0.0
    gx = _grid_lines(-a, a, np.unique(c[:, 0]), band, ex, step_far=step_mm)
    gy = _grid_lines(-b, b, np.unique(c[:, 1]), band, ey, step_far=step_mm)
    XX, YY = np.meshgrid(gx, gy)  # (ny, nx)
    Z = surface_depth(params, holder, XX, YY)
    V = np.stack([XX, YY, Z], -1).reshape(-1, 3).astype(np.float32)
    ny, nx = XX.shape
    F = _quad_faces(ny, nx)
    cx = 0.5 * (gx[:-1] + gx[1:])
    cy = 0.5 * (gy[:-1] + gy[1:])
    inside = inside_pocket(*np.meshgrid(cx, cy), c).ravel()  # (ny-1)*(nx-1) cells
    keep = np.concatenate([~inside, ~inside])  # both triangles of each cell
    F = orient_faces(V, F[keep], np.array([0.0, 0.0, -1.0]))
    UV = np.column_stack([(V[:, 0] + a) / (2 * a), (V[:, 1] + b) / (2 * b)]).astype(np.float32)
    top = MeshData("top", V, F, _vertex_normals(V, F), UV)
    # walls: one strip per contour edge through the face's boundary vertices
    D = params["pocket_depth_mm"]
    walls = []
    nxt = np.roll(c, -1, axis=0)
    for k, (p, q) in enumerate(zip(c, nxt)):
        inward = np.array([-(q - p)[1], (q - p)[0]]) / np.linalg.norm(q - p)
        if p[1] == q[1]:
            iy = int(np.flatnonzero(np.isclose(gy, p[1]))[0])
            ix = np.flatnonzero((gx >= min(p[0], q[0]) - 1e-9) & (gx <= max(p[0], q[0]) + 1e-9))
            top_pts = np.column_stack([gx[ix], np.full(ix.size, p[1]), Z[iy, ix]])
        else:
            ix = int(np.flatnonzero(np.isclose(gx, p[0]))[0])
            iy = np.flatnonzero((gy >= min(p[1], q[1]) - 1e-9) & (gy <= max(p[1], q[1]) + 1e-9))
            top_pts = np.column_stack([np.full(iy.size, p[0]), gy[iy], Z[iy, ix]])
        bot = top_pts.copy()
        bot[:, 2] = D
        Vw = np.stack([top_pts, bot], 0).reshape(-1, 3).astype(np.float32)  # 2 x n
        Fw = orient_faces(Vw, _quad_faces(2, len(top_pts)), np.array([inward[0], inward[1], 0.0]))
        del k
        walls.append(MeshData("wall", Vw, Fw))
    # floor: the rectangles of the contour's own coordinate grid that lie inside
    xs, ys = np.unique(c[:, 0]), np.unique(c[:, 1])
    floor = []
    for i in range(len(xs) - 1):
        for j in range(len(ys) - 1):
            if inside_pocket(np.array([0.5 * (xs[i] + xs[i + 1])]),
                              np.array([0.5 * (ys[j] + ys[j + 1])]), c)[0]:
                floor.append(_rect_mesh("floor", xs[i], xs[i + 1], ys[j], ys[j + 1], D))
    return top, _merge("walls", walls), _merge("floor", floor)


def _revolve(name: str, profile: np.ndarray, axis_x: float, axis_z: float,
             segments: int = 256) -> MeshData:
    """Surface of revolution about the axis parallel to Y through ``(axis_x, ., axis_z)``;
    ``profile`` is (n, 2) of (y, radius). Each profile segment gets its own ring of vertices
    (creases stay sharp) with the analytic normals."""
    th = np.linspace(0.0, 2 * np.pi, segments + 1)
    radial = np.stack([np.sin(th), np.zeros_like(th), -np.cos(th)], 1)  # theta = 0 faces -Z
    Vs, Ns, Fs, off = [], [], [], 0
    for (y0, r0), (y1, r1) in zip(profile[:-1], profile[1:]):
        t = np.array([y1 - y0, r1 - r0])
        ln = np.hypot(*t)
        if ln == 0:
            continue
        n_y, n_r = -t[1] / ln, t[0] / ln
        ring = []
        for y, r in ((y0, r0), (y1, r1)):
            P = np.column_stack([axis_x + r * radial[:, 0], np.full(len(th), y),
                                 axis_z + r * radial[:, 2]])
            ring.append(P)
        V = np.concatenate(ring)
        N = np.tile(np.column_stack([n_r * radial[:, 0], np.full(len(th), n_y),
                                     n_r * radial[:, 2]]), (2, 1))
        F = _quad_faces(2, len(th))
        F = orient_faces(V, F, N[F[:, 0]] + N[F[:, 1]] + N[F[:, 2]])
        Vs.append(V)
        Ns.append(N)
        Fs.append(F + off)
        off += len(V)
    return MeshData(name, np.concatenate(Vs).astype(np.float32), np.concatenate(Fs),
                    np.concatenate(Ns).astype(np.float32))


def _cutter_meshes(cut: dict, holder: Holder) -> tuple[MeshData, MeshData]:
    """The disc cutter: (ring, hub + shaft), axle along Y at X = cut['x_mm']."""
    R, p, wt = cut["radius_mm"], cut["protrusion_mm"], cut["tip_half_width_mm"]
    zc = R - p  # the ring's front point is p in front of the top face
    c = holder.corners_mm
    half_w = float(np.max(np.abs(c[:, 1]))) - 0.5   # shaft from wall to wall
    rh, rs, wh, wr = 0.42 * R, 0.17 * R, 50.0, 22.0
    ring = np.array([[-wr, rh + 6], [-wr, R - 38], [-wt - 5, R - 7], [-wt, R], [wt, R],
                     [wt + 5, R - 7], [wr, R - 38], [wr, rh + 6]])
    hub = np.array([[-half_w, 0.0], [-half_w, rs], [-wh, rs], [-wh, rh], [-wr, rh + 6],
                    [wr, rh + 6], [wh, rh], [wh, rs], [half_w, rs], [half_w, 0.0]])
    return (_revolve("cutter_ring", ring, cut["x_mm"], zc),
            _revolve("cutter_hub", hub, cut["x_mm"], zc))


def _lump_mesh(lump: dict, name: str) -> MeshData:
    """A slurry lump: a flattened sphere with a random low-frequency displacement, sunk 35 %
    of its height into the face."""
    rng = np.random.default_rng(lump["shape_seed"])
    nt, npf = 40, 80
    t = np.linspace(0, np.pi, nt)
    f = np.linspace(0, 2 * np.pi, npf, endpoint=False)
    T, P = np.meshgrid(t, f, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)
    s = np.ones(T.shape)
    for i in range(14):
        k = rng.normal(size=3)
        k *= rng.uniform(1.5, 4.0) * (1.0 + i // 5) / np.linalg.norm(k)
        s += rng.uniform(0.05, 0.14) / (1.0 + i // 5) * np.cos(d @ k + rng.uniform(0, 2 * np.pi))
    P3 = d * s[..., None] * np.array([lump["rx_mm"], lump["ry_mm"], lump["rz_mm"]])
    yaw = math.radians(lump["yaw_deg"])
    Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0],
                   [0, 0, 1]])
    P3 = P3 @ Rz.T + np.array([lump["x_mm"], lump["y_mm"], 0.35 * lump["rz_mm"]])
    V = P3.reshape(-1, 3)
    # faces of a (nt x npf) grid closed in phi
    i, j = np.meshgrid(np.arange(nt - 1), np.arange(npf), indexing="ij")
    v0 = i * npf + j
    v1 = i * npf + (j + 1) % npf
    v2, v3 = v0 + npf, v1 + npf
    F = np.concatenate([np.stack([v0.ravel(), v2.ravel(), v1.ravel()], 1),
                        np.stack([v1.ravel(), v2.ravel(), v3.ravel()], 1)])
    area = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    F = F[area > 1e-9]
    cen = V[F].mean(axis=1) - np.array([lump["x_mm"], lump["y_mm"], 0.35 * lump["rz_mm"]])
    F = orient_faces(V, F, cen)  # outwards
    V = V.astype(np.float32)
    return MeshData(name, V, F, _vertex_normals(V, F))


def build_geometry(params: dict, holder: Holder,
                   step_mm: float = 0.2) -> dict[str, list[MeshData]]:
    """Every mesh of the scene in the holder frame, grouped by material; ``step_mm``: the
    coarsest spacing of the top face's grid near the contour (about a pixel's footprint)."""
    a, b = holder.outer_length_x_mm / 2, holder.outer_width_y_mm / 2
    top, walls, floor = _top_and_walls(params, holder, step_mm)
    pl = params["plate"]
    g, dz, L, back = pl["gap_mm"], pl["dz_mm"], 1500.0, 60.0
    A, B = a + g, b + g
    box = (-L, L, -L, L)
    plate = [_rect_mesh("plate", -L, L, B, L, dz, uv_box=box),
             _rect_mesh("plate", -L, L, -L, -B, dz, uv_box=box),
             _rect_mesh("plate", -L, -A, -B, B, dz, uv_box=box),
             _rect_mesh("plate", A, L, -B, B, dz, uv_box=box)]
    rect = holder.outer_rectangle_mm
    block, hole = [], []
    for p, q in zip(rect, np.roll(rect, -1, axis=0)):
        out = np.array([(q - p)[1], -(q - p)[0]]) / np.linalg.norm(q - p)
        block.append(_wall_mesh("block", p, q, 0.0, 0.0, back, out))
        s = np.sign(p) * [A, B]
        t = np.sign(q) * [A, B]
        hole.append(_wall_mesh("hole", s, t, dz, dz, back, -out))
    groups = {"top": [top], "walls": [walls], "floor": [floor],
              "plate": [_merge("plate", plate)],
              "dark": [_merge("dark", block + hole + [_rect_mesh("gap", -A, A, -B, B, back)])]}
    if params["cutter"]:
        ring, hub = _cutter_meshes(params["cutter"], holder)
        groups["cutter_ring"] = [ring]
        groups["cutter_hub"] = [hub]
    for i, lump in enumerate(params["slurry"]):
        groups[f"slurry_{i}"] = [_lump_mesh(lump, f"slurry_{i}")]
    return groups



# ------------------------------------------------------------------------------------------
# textures
def top_textures(params: dict, holder: Holder, texel_mm: float = 0.25) -> dict:
    """Albedo, roughness, metallic and clear-coat maps of the top face (float32, rows along
    +Y from -b, columns along +X from -a, the uv of the face mesh)."""
    rng = np.random.default_rng(params["texture_seed"])
    a, b = holder.outer_length_x_mm / 2, holder.outer_width_y_mm / 2
    w, h = int(math.ceil(2 * a / texel_mm)), int(math.ceil(2 * b / texel_mm))
    t = 0.25 / texel_mm
    X = (-a + (np.arange(w, dtype=np.float32) + 0.5) * texel_mm)[None, :]
    Y = (-b + (np.arange(h, dtype=np.float32) + 0.5) * texel_mm)[:, None]
    gr = params["grime"]
    alb = 1.0 + gr * (0.7 * fractal_noise((h, w), rng, 160 * t, 5)
                      + 0.3 * fractal_noise((h, w), rng, 12 * t, 3))
    # fly-cutting arcs modulate the albedo a little
    cx, cy = rng.uniform(-1.5, 1.5) * a, rng.choice([-1, 1]) * rng.uniform(2.5, 4.0) * b
    r = np.sqrt((X - cx) ** 2 + (Y - cy) ** 2)
    pitch = rng.uniform(0.8, 1.6)
    alb += 0.5 * gr * np.sin(2 * np.pi * r / pitch + 1.5 * fractal_noise((h, w), rng, 200 * t, 2))
    rough = params["steel_roughness"] * (1.0 + 0.04 * fractal_noise((h, w), rng, 40 * t, 3))
    metal = np.full((h, w), 0.35, np.float32)
    coat = np.zeros((h, w), np.float32)
    if params["corrosion"] > 0:
        f = fractal_noise((h, w), rng, 240 * t, 5)
        thr = np.quantile(f[::8, ::8], 1.0 - params["corrosion"])
        blot = np.clip((f - thr) / 0.35, 0.0, 1.0)
        grain = 0.5 + 0.5 * np.clip(fractal_noise((h, w), rng, 6 * t, 3), -1, 1)
        alb *= 1.0 - 0.55 * blot * (0.6 + 0.4 * grain)
        rough = rough + (0.9 - rough) * blot
        metal = metal * (1.0 - 0.9 * blot)
    c = holder.corners_mm
    for _ in range(params["wet_patches"]):
        # wet patches lie mostly near the pocket (water runs into it)
        if rng.uniform() < 0.7:
            k, _f, q = point_on_contour(rng, c)
            q = q + outward_normal(c, k) * rng.uniform(0.0, 25.0)
        else:
            q = np.array([rng.uniform(-a, a), rng.uniform(-b, b)])
        rx, ry = rng.uniform(8.0, 40.0), rng.uniform(6.0, 25.0)
        ang = rng.uniform(0, np.pi)
        u = ((X - q[0]) * np.cos(ang) + (Y - q[1]) * np.sin(ang)) / rx
        v = (-(X - q[0]) * np.sin(ang) + (Y - q[1]) * np.cos(ang)) / ry
        edge = 0.25 * fractal_noise((h, w), rng, 30 * t, 3)
        m = np.clip((1.0 - np.sqrt(u * u + v * v) + edge) / 0.15, 0.0, 1.0)
        alb *= 1.0 - 0.35 * m
        coat = np.maximum(coat, m)
    return {"albedo": (params["steel_albedo"] * np.clip(alb, 0.05, 1.6)).astype(np.float32),
            "roughness": np.clip(rough, 0.05, 1.0).astype(np.float32),
            "metallic": np.clip(metal, 0.0, 1.0).astype(np.float32),
            "coat": coat.astype(np.float32)}



# ------------------------------------------------------------------------------------------
# truth
def _ray_hits(origin: np.ndarray, targets: np.ndarray, V: np.ndarray, F: np.ndarray,
              eps: float = 1e-3) -> np.ndarray:
    """For rays origin -> target (segment parameter in (0, 1 - eps)): does any triangle of
    (V, F) cut the segment? (Moller-Trumbore, vectorised.)"""
    d = targets - origin  # (R, 3)
    v0, e1, e2 = V[F[:, 0]], V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
    hit = np.zeros(len(targets), bool)
    for r in range(len(targets)):
        p = np.cross(d[r], e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origin - v0
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d[r]) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit[r] = bool(np.any(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > eps)
                             & (t < 1 - eps)))
    return hit


def hidden_corners(params: dict, holder: Holder, pose: Pose, geometry: dict,
                   probe_mm: float = 1.5) -> dict[int, list[str]]:
    """Corners whose neighbourhood (the corner and the points ``probe_mm`` along its two
    edges) is covered by the cutter or a slurry lump, or bitten by a chip: {index: reasons}."""
    c = holder.corners_mm
    n = len(c)
    prev, nxt = np.roll(c, 1, axis=0), np.roll(c, -1, axis=0)
    u1 = (prev - c) / np.linalg.norm(prev - c, axis=1)[:, None]
    u2 = (nxt - c) / np.linalg.norm(nxt - c, axis=1)[:, None]
    probes = np.stack([c, c + probe_mm * u1, c + probe_mm * u2], 1)  # (n, 3, 2)
    P = np.concatenate([probes.reshape(-1, 2), np.zeros((3 * n, 1))], 1)
    origin = -pose.R.T @ pose.t_mm
    out: dict[int, list[str]] = {}
    for key, meshes in geometry.items():
        if not (key.startswith("cutter") or key.startswith("slurry")):
            continue
        why = "cutter" if key.startswith("cutter") else "slurry"
        for m in meshes:
            V, F = m.V.astype(np.float64), m.F
            # only triangles in front of the face can hide a point of it
            F = F[V[F][:, :, 2].min(axis=1) < 0]
            if len(F) == 0:
                continue
            hit = _ray_hits(origin, P, V, F).reshape(n, 3).any(axis=1)
            for i in np.flatnonzero(hit):
                out.setdefault(int(i), [])
                if why not in out[int(i)]:
                    out[int(i)].append(why)
    for ch in params["chips"]:
        k = ch["edge"]
        d = nxt[k] - c[k]
        e = d / np.linalg.norm(d)
        q = probes.reshape(-1, 2) - [ch["x_mm"], ch["y_mm"]]
        ua = (q @ e) / (ch["half_length_mm"] + 1.0)
        ub = (q @ np.array([-e[1], e[0]])) / (ch["half_width_mm"] + 1.0)
        inside = ((ua * ua + ub * ub) < 1.0).reshape(n, 3).any(axis=1)
        for i in np.flatnonzero(inside):
            out.setdefault(int(i), [])
            if "chip" not in out[int(i)]:
                out[int(i)].append("chip")
    return dict(sorted(out.items()))


def edge_radius_stats(params: dict, holder: Holder, step_mm: float = 5.0) -> list[dict]:
    """Per contour edge: mean, min and max radius (mm) and samples every ``step_mm``."""
    c = holder.corners_mm
    out = []
    for k, (p, q) in enumerate(zip(c, np.roll(c, -1, axis=0))):
        L = float(np.linalg.norm(q - p))
        s = np.linspace(0.0, 1.0, max(2, int(round(L / 1.0)) + 1))
        pts = p + s[:, None] * (q - p)
        r = edge_radius(params, pts[:, 0], pts[:, 1])
        ss = np.linspace(0.0, 1.0, max(2, int(round(L / step_mm)) + 1))
        rs = edge_radius(params, p[0] + ss * (q - p)[0], p[1] + ss * (q - p)[1])
        out.append({"edge": k, "radius_mean_mm": float(r.mean()),
                    "radius_min_mm": float(r.min()), "radius_max_mm": float(r.max()),
                    "radius_step_mm": L / (len(ss) - 1),
                    "radius_samples_mm": [round(float(x), 3) for x in rs],
                    "chips": [i for i, ch in enumerate(params["chips"]) if ch["edge"] == k]})
    return out

