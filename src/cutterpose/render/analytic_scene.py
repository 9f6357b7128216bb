"""The analytic renderer's scene: the holder's top face, pocket walls and floor, its outer
walls and the cutterhead, with their textures (:class:`AnalyticScene`), each viewing ray
intersected with them in closed form. Convention and radiometry:
:mod:`cutterpose.render.analytic`."""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..errors import InputError
from ..geometry.holder import Holder
from ..geometry.pose import Pose
from .analytic_presets import RenderSettings
from .sensor import fractal_noise, light_falloff, shade_points

__all__ = ["AnalyticScene", "BACKGROUND", "TOP", "FLOOR", "CUTTERHEAD", "OUTER_WALL", "WALL"]

# surface labels of the label image (pocket walls: WALL + edge index, so that the edge between
# two walls is antialiased too)
BACKGROUND, TOP, FLOOR, CUTTERHEAD, OUTER_WALL, WALL = 0, 1, 2, 3, 4, 10


def _sample(tex: np.ndarray, u, v) -> np.ndarray:
    """Bilinear lookup of ``tex`` at texel coordinates ``(u, v)`` (any shape, reflected at the
    border) through ``cv2.remap``, which needs 2-D maps below 32767 on a side."""
    u = np.asarray(u, np.float32)
    v = np.asarray(v, np.float32)
    shape = u.shape
    n = u.size
    if n == 0:
        return np.zeros(shape, np.float32)
    w = 1024
    rows = -(-n // w)
    pad = rows * w - n
    mu = np.concatenate([u.ravel(), np.zeros(pad, np.float32)]).reshape(rows, w)
    mv = np.concatenate([v.ravel(), np.zeros(pad, np.float32)]).reshape(rows, w)
    out = cv2.remap(tex, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out.ravel()[:n].reshape(shape)


# ------------------------------------------------------------------------------------------
# the scene
class _Texture:
    """A float32 texture over a rectangle of a surface's own 2-D coordinates (mm)."""

    def __init__(self, data: np.ndarray, x0_mm: float, y0_mm: float, texel_mm: float):
        self.data = data
        self.x0, self.y0, self.texel = x0_mm, y0_mm, texel_mm

    def __call__(self, x_mm, y_mm) -> np.ndarray:
        return _sample(self.data, (x_mm - self.x0) / self.texel, (y_mm - self.y0) / self.texel)


class AnalyticScene:
    """Geometry, pose and textures of one image."""

    def __init__(self, pose: Pose, holder: Holder, settings: RenderSettings,
                 rng: np.random.Generator, texel_mm: float = 0.25):
        self.pose, self.holder, self.s = pose, holder, settings
        self.texel_mm = float(texel_mm)
        R = pose.R
        self.Rt = R.T.astype(np.float64)
        self.o_h = -R.T @ pose.t_mm
        if self.o_h[2] >= 0:
            raise InputError("the camera must look at the top face of the holder (the camera "
                             f"centre is at Z = {self.o_h[2]:.1f} mm in the holder frame; it must "
                             "be on the -Z side)")
        c = holder.corners_mm
        self.edges = np.stack([c, np.roll(c, -1, axis=0)], axis=1)  # (N, 2, 2)
        d = self.edges[:, 1] - self.edges[:, 0]
        self.inward = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
        self.arc0 = np.concatenate([[0.0], np.cumsum(np.linalg.norm(d, axis=1))[:-1]])
        a, b = holder.outer_length_x_mm / 2, holder.outer_width_y_mm / 2
        self.a, self.b = a, b
        rect = holder.outer_rectangle_mm
        self.rect_edges = np.stack([rect, np.roll(rect, -1, axis=0)], axis=1)
        dr = self.rect_edges[:, 1] - self.rect_edges[:, 0]
        self.rect_outward = np.column_stack([dr[:, 1], -dr[:, 0]]) / np.linalg.norm(
            dr, axis=1)[:, None]
        self.rect_arc0 = np.concatenate([[0.0], np.cumsum(np.linalg.norm(dr, axis=1))[:-1]])
        self._make_textures(rng)
        r_edge = rng.spawn(1)[0]  # after the textures' streams: they stay as they were
        self.edge_radius = np.zeros(len(c))
        if settings.edge_radius_mm > 0:
            if settings.edge_shape not in ("round", "chamfer"):
                raise InputError("edge_shape must be 'round' or 'chamfer', got "
                                 f"{settings.edge_shape!r}")
            self.edge_radius = settings.edge_radius_mm * (
                1.0 + settings.edge_radius_spread * r_edge.uniform(-1, 1, len(c)))
        self.edge_len = np.linalg.norm(d, axis=1)
        self.edge_dir = d / self.edge_len[:, None]

    # --- textures --------------------------------------------------------------------------
    def _make_textures(self, rng: np.random.Generator):
        s, a, b = self.s, self.a, self.b
        # one stream per surface: a setting of one surface does not reshuffle the others
        rng, r_floor, r_cut, r_wall = rng.spawn(4)
        margin = 10.0
        texel = self.texel_mm
        t = 0.25 / texel  # texture scales below are written in texels of 0.25 mm
        w = int(math.ceil((2 * a + 2 * margin) / texel))
        h = int(math.ceil((2 * b + 2 * margin) / texel))
        x0, y0 = -a - margin, -b - margin
        X = (x0 + (np.arange(w, dtype=np.float32) + 0.5) * texel)[None, :]
        Y = (y0 + (np.arange(h, dtype=np.float32) + 0.5) * texel)[:, None]
        alb = 1.0 + s.texture * (0.7 * fractal_noise((h, w), rng, 160 * t, 5)
                                 + 0.3 * fractal_noise((h, w), rng, 12 * t, 3))
        gloss = np.ones((h, w), np.float32)
        # fly-cutting marks: arcs round a cutter centre off the part; a jittered pitch of about
        # a millimetre (a few pixels) and a slow beat between passes. The marks modulate the
        # specular lobe more than the albedo: that is what makes machined steel look machined.
        cx, cy = rng.uniform(-1.5, 1.5) * a, rng.choice([-1, 1]) * rng.uniform(2.5, 4.0) * b
        r = np.sqrt((X - cx) ** 2 + (Y - cy) ** 2)
        pitch = rng.uniform(0.8, 1.6)
        phase = 2 * np.pi * (r / pitch) + 1.5 * fractal_noise((h, w), rng, 200 * t, 2)
        beat = 0.5 + 0.5 * np.sin(2 * np.pi * r / rng.uniform(15.0, 40.0))
        # marks finer than two texels average out within a pixel: fade them
        fade = float(np.clip(pitch / (2 * texel) - 1.0, 0.0, 1.0))
        marks = fade * (np.sin(phase) + 0.5 * np.sin(2 * phase + 1.0)) * (0.5 + beat)
        alb += s.machining_marks * marks
        gloss *= np.clip(1.0 + 3.0 * s.machining_marks * marks, 0.0, None)
        # fine streaks along the cutting direction (noise blurred along X)
        streak = cv2.GaussianBlur(rng.standard_normal((h, w), dtype=np.float32), (0, 0),
                                  sigmaX=6.0 * t, sigmaY=max(0.5, 0.6 * t))
        alb += 0.5 * s.texture * streak / max(float(streak.std()), 1e-6)
        # scratches: thin antialiased lines, a little brighter or darker than the steel
        scr = np.zeros((h, w), np.float32)
        for _ in range(int(s.scratches)):
            p = np.array([rng.uniform(0, w), rng.uniform(0, h)])
            ang = rng.uniform(0, np.pi)
            ln = rng.uniform(5.0, 100.0) / texel
            q = p + ln * np.array([np.cos(ang), np.sin(ang)])
            cv2.line(scr, (int(p[0] * 16), int(p[1] * 16)), (int(q[0] * 16), int(q[1] * 16)),
                     float(rng.choice([-1.0, 1.0]) * rng.uniform(0.15, 0.35)), 1, cv2.LINE_AA, 4)
        alb += scr
        if s.corrosion > 0:
            self._corrode(alb, gloss, rng, t)
        if s.edge_wear_mm > 0:
            self._wear_edge(alb, gloss, rng, t, x0, y0, texel)
        self.top_albedo = _Texture((s.top_albedo * np.clip(alb, 0.05, 2.0)).astype(np.float32),
                                   x0, y0, texel)
        self.top_gloss = _Texture(np.clip(gloss, 0, 1).astype(np.float32), x0, y0, texel)
        # floor and cutterhead: dark, greasy, coarse texture
        texel = 1.0
        w2, h2 = 1600, 1200
        ch = np.exp(0.35 * fractal_noise((h2, w2), r_cut, 150, 5)).astype(np.float32)
        self.cut_albedo = _Texture((s.cutterhead_albedo * ch).astype(np.float32),
                                   -w2 / 2, -h2 / 2, texel)
        fl = np.exp(0.35 * fractal_noise((int(2 * b) + 20, int(2 * a) + 20), r_floor, 40, 4))
        self.floor_albedo = _Texture((s.floor_albedo * fl).astype(np.float32), -a - 10, -b - 10,
                                     1.0)
        per = float(np.sum(np.linalg.norm(self.edges[:, 1] - self.edges[:, 0], axis=1)))
        per_o = 2 * (2 * a + 2 * b)
        # (depth, arc length) at 0.5 mm; reflected beyond 256 mm of depth
        wl = np.exp(0.3 * fractal_noise((512, int(max(per, per_o) * 2) + 4), r_wall, 30,
                                        4)).astype(np.float32)
        self.wall_tex = _Texture(wl, 0.0, 0.0, 0.5)

    def _corrode(self, alb: np.ndarray, gloss: np.ndarray, rng, t: float) -> None:
        """Corrosion on the top face's albedo and gloss (in place; ``t``: texels per 0.25 mm)."""
        s = self.s
        h, w = alb.shape
        # corrosion blotches: thresholded low-frequency noise, dark, dull and pitted
        f = fractal_noise((h, w), rng, 240 * t, 5)
        thr = np.quantile(f[::8, ::8], 1.0 - s.corrosion)
        blot = np.clip((f - thr) / 0.35, 0.0, 1.0)
        grain = 0.5 + 0.5 * np.clip(fractal_noise((h, w), rng, 6 * t, 3), -1, 1)
        pits = (rng.random((h, w), dtype=np.float32) < 0.004 / t**2 * blot).astype(np.float32)
        pits = cv2.GaussianBlur(pits, (0, 0), max(0.5, 0.7 * t)) * 2.5
        alb *= (1.0 - s.corrosion_darkening * blot * (0.6 + 0.4 * grain)) * np.clip(
            1.0 - pits, 0.2, 1.0)
        gloss *= 1.0 - 0.9 * blot

    def _wear_edge(self, alb: np.ndarray, gloss: np.ndarray, rng, t: float, x0: float,
                   y0: float, texel: float) -> None:
        """The worn band along the inner contour on the top face's albedo and gloss (in place;
        the texture's origin ``(x0, y0)`` and ``texel`` mm)."""
        s = self.s
        h, w = alb.shape
        # worn band along the inner contour: a rounded, chipped, dull edge of varying width.
        # Its normal turns away from the light, so it darkens towards the contour; chips are
        # bites of the band into the face.
        pocket = np.zeros((h, w), np.uint8)
        pts = np.round((self.holder.corners_mm - [x0, y0]) / texel * 16).astype(np.int32)
        cv2.fillPoly(pocket, [pts], 1, cv2.LINE_8, 4)
        dist_mm = cv2.distanceTransform(1 - pocket, cv2.DIST_L2, 5) * texel
        width = s.edge_wear_mm * np.clip(1.0 + 0.7 * fractal_noise((h, w), rng, 120 * t, 3),
                                         0.15, 3.0)
        chips = np.clip(fractal_noise((h, w), rng, 10 * t, 2) - 1.2, 0.0, None) * 2.5
        width = width * (1.0 + chips)
        band = np.clip(1.0 - dist_mm / width, 0.0, 1.0) ** 0.8
        grime = 0.5 + 0.5 * np.clip(fractal_noise((h, w), rng, 4 * t, 2), -1, 1)
        alb *= 1.0 - s.edge_wear_darkening * band * (0.75 + 0.25 * grime)
        gloss *= 1.0 - band

    # --- ray casting -----------------------------------------------------------------------
    def trace(self, xn: np.ndarray, yn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Labels (uint8) and grey levels (float32 DN, before blur and noise) of the rays of
        normalised coordinates ``(xn, yn)`` (1-D float32 arrays)."""
        s = self.s
        xn = xn.astype(np.float32, copy=False)
        yn = yn.astype(np.float32, copy=False)
        Rt = self.Rt.astype(np.float32)
        o = self.o_h.astype(np.float32)
        dx = Rt[0, 0] * xn + Rt[0, 1] * yn + Rt[0, 2]
        dy = Rt[1, 0] * xn + Rt[1, 1] * yn + Rt[1, 2]
        dz = Rt[2, 0] * xn + Rt[2, 1] * yn + Rt[2, 2]
        norm_d = np.sqrt(1.0 + xn * xn + yn * yn)
        falloff = light_falloff(xn, yn, s)
        n = xn.size
        label = np.zeros(n, np.uint8)
        value = np.full(n, np.float32(s.ambient_dn), np.float32)
        ok = dz > 1e-6
        with np.errstate(divide="ignore", invalid="ignore"):
            s0 = np.where(ok, (0.0 - o[2]) / dz, np.nan).astype(np.float32)
        X0 = o[0] + s0 * dx
        Y0 = o[1] + s0 * dy
        in_rect = ok & (np.abs(X0) <= self.a) & (np.abs(Y0) <= self.b)
        in_pocket = np.zeros(n, bool)
        ir = np.flatnonzero(in_rect)
        in_pocket[ir] = _inside_axis_polygon(X0[ir], Y0[ir], self.edges)
        top = in_rect & ~in_pocket
        # cos(i) of a face with normal -Z: n . (-d/|d|) in the holder frame = dz / |d|
        cos_flat = dz / norm_d
        if self.edge_radius.max() > 0:
            self._trace_broken_edges(ok, top, in_pocket, X0, Y0, s0, (dx, dy, dz, norm_d),
                                     falloff, label, value)
        i = np.flatnonzero(top)
        if i.size:
            label[i] = TOP
            value[i] = shade_points(cos_flat[i], s0[i] * norm_d[i],
                                    self.top_albedo(X0[i], Y0[i]), self.top_gloss(X0[i], Y0[i]),
                                    falloff[i], s)
        rays = (X0, Y0, s0, dx, dy, norm_d, falloff, cos_flat)
        # pocket: first wall crossed between Z = 0 and the floor, else the floor
        i = np.flatnonzero(in_pocket)
        if i.size:
            D = np.float32(s.pocket_depth_mm)
            s1 = (D - o[2]) / dz[i]
            X1, Y1 = o[0] + s1 * dx[i], o[1] + s1 * dy[i]
            frac, edge = _first_crossing(X0[i], Y0[i], X1, Y1, self.edges)
            self._shade_behind(i, D, (s1, X1, Y1, frac, edge), rays, label, value,
                               (FLOOR, self.floor_albedo),
                               (lambda e: WALL + e.astype(np.uint8), self.edges, self.inward,
                                self.arc0, s.wall_albedo))
        # outside the holder: its outer side walls, else the cutterhead
        i = np.flatnonzero(ok & ~in_rect)
        if i.size:
            C = np.float32(s.cutterhead_depth_mm)
            s1 = (C - o[2]) / dz[i]
            X1, Y1 = o[0] + s1 * dx[i], o[1] + s1 * dy[i]
            # only segments whose bounding box meets the rectangle can hit a side wall
            near = np.flatnonzero((np.minimum(X0[i], X1) <= self.a)
                                  & (np.maximum(X0[i], X1) >= -self.a)
                                  & (np.minimum(Y0[i], Y1) <= self.b)
                                  & (np.maximum(Y0[i], Y1) >= -self.b))
            frac = np.full(i.size, np.inf, np.float32)
            edge = np.full(i.size, -1, np.int64)
            frac[near], edge[near] = _first_crossing(X0[i[near]], Y0[i[near]], X1[near],
                                                     Y1[near], self.rect_edges)
            self._shade_behind(i, C, (s1, X1, Y1, frac, edge), rays, label, value,
                               (CUTTERHEAD, self.cut_albedo),
                               (lambda e: OUTER_WALL, self.rect_edges, self.rect_outward,
                                self.rect_arc0, s.outer_wall_albedo))
        return label, value

    def _shade_behind(self, i, depth, hits, rays, label, value, plane, walls) -> None:
        """Label and shade the rays ``i`` that go on behind ``Z = 0`` into a region bounded by
        walls and a back plane at ``depth`` (the pocket and its floor, or the holder's outer
        walls and the cutterhead): ``hits = (s1, X1, Y1, frac, edge)``, each ray's depth and
        point on the back plane and the first wall it crosses (``edge < 0``: none);
        ``plane = (label, albedo texture)``, ``walls = (label of edges e, edges, normals,
        arc0, albedo)``."""
        s1, X1, Y1, frac, edge = hits
        X0, Y0, s0, dx, dy, norm_d, falloff, cos_flat = rays
        wall = edge >= 0
        pi = i[~wall]
        label[pi] = plane[0]
        value[pi] = shade_points(cos_flat[pi], s1[~wall] * norm_d[pi],
                                 plane[1](X1[~wall], Y1[~wall]), np.float32(0.1),
                                 falloff[pi], self.s)
        wi = i[wall]
        if wi.size:
            e = edge[wall]
            wall_label, edges, normals, arc0, albedo = walls
            label[wi] = wall_label(e)
            value[wi] = self._shade_wall(
                wi, e, frac[wall], s1[wall], depth, (X0, Y0, s0, X1[wall], Y1[wall]),
                (dx, dy, norm_d, falloff), edges, normals, arc0, albedo)

    def _trace_broken_edges(self, ok, top, in_pocket, X0, Y0, s0, ray, falloff, label, value):
        """Rays that meet the broken pocket edge: shaded here and removed from ``top`` /
        ``in_pocket`` (edited in place); rays that cross the cut-away band and miss it go on
        into the pocket.

        In the local frame of edge k (``s`` outwards from the pocket, ``z`` depth, both 0 at the
        design edge) a ray leaving the plane ``Z = 0`` at ``s0`` goes ``s = s0 + mu d_s``,
        ``z = mu d_z`` (``mu`` in camera-depth units). Fillet (circle of radius r about
        ``(r, r)``, the quadrant ``s, z <= r``): the entry root of
        ``(d_s^2 + d_z^2) mu^2 + 2 ((s0 - r) d_s - r d_z) mu + (s0 - r)^2 = 0``; chamfer (the
        plane ``s + z = r``): ``mu = (r - s0) / (d_s + d_z)``.
        """
        dx, dy, dz, norm_d = ray
        rmax = float(self.edge_radius.max())
        # a ray reaches the break within a few radii of the edge (|d_s / d_z| < 1 in the rig)
        near = ok & (top | in_pocket)
        idx = np.flatnonzero(near)
        if not idx.size:
            return
        best = np.full(idx.size, np.inf)
        hit_e = np.full(idx.size, -1, np.int64)
        band = np.zeros(idx.size, bool)
        X, Y = X0[idx].astype(np.float64), Y0[idx].astype(np.float64)
        DX, DY, DZ = dx[idx].astype(np.float64), dy[idx].astype(np.float64), dz[idx].astype(
            np.float64)
        n_s = np.zeros(idx.size)
        n_z = np.zeros(idx.size)
        round_ = self.s.edge_shape == "round"
        for k, r in enumerate(self.edge_radius):
            o = -self.inward[k]
            tk = self.edge_dir[k]
            e0 = self.edges[k, 0]
            sk = (X - e0[0]) * o[0] + (Y - e0[1]) * o[1]
            tt = (X - e0[0]) * tk[0] + (Y - e0[1]) * tk[1]
            m = (sk > -3 * rmax - 1) & (sk < r) & (tt >= 0) & (tt <= self.edge_len[k])
            band |= m & (sk >= 0)
            j = np.flatnonzero(m)
            if not j.size:
                continue
            s_0, ds = sk[j], DX[j] * o[0] + DY[j] * o[1]
            dzj = DZ[j]
            with np.errstate(invalid="ignore", divide="ignore"):
                if round_:
                    A = ds * ds + dzj * dzj
                    B = (s_0 - r) * ds - r * dzj
                    disc = B * B - A * (s_0 - r) ** 2
                    mu = (-B - np.sqrt(disc)) / A
                else:
                    mu = (r - s_0) / (ds + dzj)
            ss, zz = s_0 + mu * ds, mu * dzj
            good = (np.isfinite(mu) & (mu >= 0) & (ss >= -1e-9) & (ss <= r + 1e-9)
                    & (zz <= r + 1e-9) & (mu < best[j]))
            g = j[good]
            best[g] = mu[good]
            hit_e[g] = k
            if round_:
                n_s[g], n_z[g] = (ss[good] - r) / r, (zz[good] - r) / r
            else:
                n_s[g], n_z[g] = -np.sqrt(0.5), -np.sqrt(0.5)
        hit = hit_e >= 0
        fi = idx[hit]
        top[idx[band]] = False
        in_pocket[idx[band & ~hit]] = True      # past the break's silhouette: into the pocket
        top[fi] = False
        in_pocket[fi] = False
        if not fi.size:
            return
        e = hit_e[hit]
        o = -self.inward[e]
        nx, ny, nz = n_s[hit] * o[:, 0], n_s[hit] * o[:, 1], n_z[hit]
        cos_i = -(nx * DX[hit] + ny * DY[hit] + nz * DZ[hit]) / norm_d[fi]
        mu = best[hit]
        Xh, Yh = X[hit] + mu * DX[hit], Y[hit] + mu * DY[hit]
        label[fi] = TOP
        value[fi] = shade_points(cos_i, (s0[fi] + mu) * norm_d[fi], self.top_albedo(Xh, Yh),
                                 self.top_gloss(Xh, Yh), falloff[fi], self.s)

    def _shade_wall(self, wi, e, f, s1, depth_mm, seg, ray, edges, normals, arc0, albedo):
        """Grey levels of rays ``wi`` that hit wall ``e`` at fraction ``f`` of their segment
        from the top plane (``X0, Y0`` at ray length ``s0``) to the plane ``depth_mm`` deep
        (``X1, Y1`` at ``s1``); the wall's normal ``normals[e]`` faces the camera side, and its
        texture runs along the outline (arc length from ``arc0``) and down the wall."""
        X0, Y0, s0, X1, Y1 = seg
        dx, dy, norm_d, falloff = ray
        sw = s0[wi] + f * (s1 - s0[wi])
        Xw = X0[wi] + f * (X1 - X0[wi])
        Yw = Y0[wi] + f * (Y1 - Y0[wi])
        nrm = normals[e].astype(np.float32)
        cos_w = -(nrm[:, 0] * dx[wi] + nrm[:, 1] * dy[wi]) / norm_d[wi]
        along = arc0[e].astype(np.float32) + np.hypot(Xw - edges[e, 0, 0], Yw - edges[e, 0, 1])
        alb = np.float32(albedo) * self.wall_tex(along, f * np.float32(depth_mm))
        return shade_points(cos_w, sw * norm_d[wi], alb, np.float32(0.5), falloff[wi], self.s)


def _inside_axis_polygon(X, Y, edges) -> np.ndarray:
    """Even-odd point-in-polygon test for a polygon with axis-parallel edges: count the edges
    parallel to Y crossed by the ray from ``(X, Y)`` towards +X (half-open in Y)."""
    inside = np.zeros(X.shape, bool)
    for (xa, ya), (xb, yb) in edges:
        if xa != xb:
            continue
        lo, hi = min(ya, yb), max(ya, yb)
        inside ^= (Y >= lo) & (Y < hi) & (X < xa)
    return inside


def _first_crossing(X0, Y0, X1, Y1, edges) -> tuple[np.ndarray, np.ndarray]:
    """First edge of an axis-parallel polygon crossed by the segments ``P0 -> P1``.

    Returns the fraction ``f`` in (0, 1] along the segment and the edge index (-1: none).
    """
    n = X0.shape[0]
    best = np.full(n, np.inf, np.float32)
    idx = np.full(n, -1, np.int64)
    DX, DY = X1 - X0, Y1 - Y0
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, ((xa, ya), (xb, yb)) in enumerate(edges):
            if ya == yb:  # edge along X at y = ya
                f = (np.float32(ya) - Y0) / DY
                c = X0 + f * DX
                lo, hi = min(xa, xb), max(xa, xb)
            else:          # edge along Y at x = xa
                f = (np.float32(xa) - X0) / DX
                c = Y0 + f * DY
                lo, hi = min(ya, yb), max(ya, yb)
            hit = (f > 0) & (f <= 1) & (c >= lo) & (c <= hi) & (f < best)
            best[hit] = f[hit]
            idx[hit] = k
    return best, idx
