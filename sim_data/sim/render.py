"""A batched camera renderer in pure JAX: ray casting against MuJoCo's primitive geoms.

It takes geom and camera poses from either engine (`Poses`, copied from MjData for `cpu`, read
from `mjx.Data` inside a jitted rollout for `mjx`) plus static arrays drawn from the MjModel once
(`SceneGeometry`), and returns frames `(B, H, W, 3) uint8`, with depth `(B, H, W) float32` (metres
along the camera axis, as `mujoco.Renderer` reports it) and the geom id per pixel `(B, H, W) int32`
(-1 for background).

Looks: per-geom colours (per-episode colours through `geom_rgb`), the floor's checker texture,
ambient + diffuse shading from the head light and the scene's lights, and shadows from the lights
that cast them. Geoms in hidden groups (3-5, as `mujoco.Renderer` hides them by default) are not
drawn. Like OpenGL with back-face culling, a ray that starts inside a convex geom does not see it.

Speed comes from tiles: the image is cut into `tile x tile` pixel tiles; each tile tests only the
geoms whose bounding sphere meets the tile's view cone (at most `max_per_tile` of each primitive
type, nearest first), and each tile's shadow rays test only the geoms whose bounding sphere, seen
along the light, meets the tile's lit points. `tile=0` tests every ray against every geom.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from sim_data.sim import scene as S

T = mujoco.mjtGeom
PRIMITIVES = (T.mjGEOM_PLANE, T.mjGEOM_SPHERE, T.mjGEOM_CAPSULE, T.mjGEOM_ELLIPSOID, T.mjGEOM_CYLINDER, T.mjGEOM_BOX)
HIDDEN_GROUPS = (3, 4, 5)
BACKGROUND_RGB = (0.08, 0.08, 0.1)
_INF = jnp.inf
_FAR = 1e30  # "no hit" where a finite value is needed
_EPS = 1e-9

HEAD_CAMERA = "head_cam"  # on the robot's neck: what the policies and the world model see
CAMERAS = (HEAD_CAMERA, "ext_cam")  # every camera of the scene (assets/home.xml)


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """What to draw and how.

    Attributes:
      height, width: frame size in pixels (64x64 default; 128x128 supported).
      camera: a camera name of the model (`head_cam`, `ext_cam`).
      shadows: cast shadow rays toward the lights that cast shadows.
      tile: tile size in pixels for culling (must divide height and width); 0 tests all geoms.
      max_per_tile: most geoms of one primitive type a tile tests (nearest first).
    """

    height: int = 64
    width: int = 64
    camera: str = HEAD_CAMERA
    shadows: bool = True
    tile: int = 16
    max_per_tile: int = 24

    def __post_init__(self):
        if self.height < 1 or self.width < 1:
            raise ValueError(f"frame size must be positive, got {self.height}x{self.width}")
        if self.tile < 0 or (self.tile and (self.height % self.tile or self.width % self.tile)):
            raise ValueError(f"tile={self.tile} must be 0 or divide the frame size {self.height}x{self.width}")
        if self.max_per_tile < 1:
            raise ValueError(f"max_per_tile must be >= 1, got {self.max_per_tile}")


@struct.dataclass
class Poses:
    """Where everything is, for a batch of states (leading axis B).

    Attributes:
      geom_xpos: (B, ngeom, 3); geom_xmat: (B, ngeom, 3, 3) world-from-geom rotations.
      cam_xpos: (B, ncam, 3); cam_xmat: (B, ncam, 3, 3).
    """

    geom_xpos: jax.Array
    geom_xmat: jax.Array
    cam_xpos: jax.Array
    cam_xmat: jax.Array


def poses_from_arrays(geom_xpos, geom_xmat, cam_xpos, cam_xmat) -> Poses:
    """Poses from MjData-shaped arrays (xmat rows of 9 or 3x3), as float32 JAX arrays."""
    lead = np.shape(geom_xpos)[:-2]
    return Poses(
        geom_xpos=jnp.asarray(geom_xpos, jnp.float32),
        geom_xmat=jnp.asarray(geom_xmat, jnp.float32).reshape(*lead, -1, 3, 3),
        cam_xpos=jnp.asarray(cam_xpos, jnp.float32),
        cam_xmat=jnp.asarray(cam_xmat, jnp.float32).reshape(*lead, -1, 3, 3))


@dataclasses.dataclass(frozen=True, eq=False)
class SceneGeometry:
    """Static arrays of one model, drawn out once (numpy; constants under jit).

    Attributes:
      groups: ((mjtGeom, geom ids (n,) int32), ...) visible geoms by primitive type.
      size: (ngeom, 3) float32 geom sizes; half_extent: (ngeom, 3) half-sizes of their bounding boxes.
      rgb: (ngeom, 3) float32 default colours (material colour where a geom has a material).
      checker: (ngeom, 2, 3) the two colours of a 2-D checker texture, and checker_cell:
        (ngeom, 2) its cell size in metres (0 where a geom has no texture).
      fovy: (ncam,) vertical field of view in degrees; cam_names: camera names.
      light_dir, light_pos: (nlight, 3); light_diffuse: (nlight, 3); light_directional,
        light_shadow: (nlight,) bool. head_ambient, head_diffuse: (3,) the head light.
      znear, zfar: clipping distances in metres.
    """

    groups: tuple
    size: np.ndarray
    half_extent: np.ndarray
    rgb: np.ndarray
    checker: np.ndarray
    checker_cell: np.ndarray
    fovy: np.ndarray
    cam_names: tuple
    light_dir: np.ndarray
    light_pos: np.ndarray
    light_diffuse: np.ndarray
    light_directional: np.ndarray
    light_shadow: np.ndarray
    head_ambient: np.ndarray
    head_diffuse: np.ndarray
    znear: float
    zfar: float
    colored: tuple  # geom ids per row of TaskState.colors
    gtype: np.ndarray  # (ngeom,) mjtGeom of each geom

    @property
    def ngeom(self) -> int:
        return self.size.shape[0]


def _half_extent(gtype: int, size: np.ndarray) -> np.ndarray:
    """Half-sizes (3,) of a primitive's bounding box in its own frame (planes: never culled)."""
    r = size[0]
    if gtype == T.mjGEOM_SPHERE:
        return np.array([r, r, r])
    if gtype == T.mjGEOM_CAPSULE:
        return np.array([r, r, size[1] + r])
    if gtype == T.mjGEOM_CYLINDER:
        return np.array([r, r, size[1]])
    if gtype in (T.mjGEOM_ELLIPSOID, T.mjGEOM_BOX):
        return np.array(size)
    return np.full(3, np.inf)


def _checker_of(model: mujoco.MjModel, g: int):
    """The two colours and cell size (m) of geom g's builtin checker texture, if it has one."""
    mat = model.geom_matid[g]
    if mat < 0:
        return np.zeros((2, 3)), np.zeros(2)
    tex = model.mat_texid[mat, mujoco.mjtTextureRole.mjTEXROLE_RGB]
    if tex < 0 or model.geom_type[g] != T.mjGEOM_PLANE:
        return np.zeros((2, 3)), np.zeros(2)
    w, h, c = model.tex_width[tex], model.tex_height[tex], model.tex_nchannel[tex]
    img = model.tex_data[model.tex_adr[tex]: model.tex_adr[tex] + w * h * c].reshape(h, w, c)[..., :3] / 255.0
    colors = np.stack([img[0, 0], img[0, w // 2 + w // 4]])  # builtin checker: 2x2 cells per texture
    repeat = model.mat_texrepeat[mat]
    cell = 2 * model.geom_size[g, :2] / np.maximum(repeat, 1e-6) / 2
    return colors * model.mat_rgba[mat, :3], cell


def scene_geometry(model: mujoco.MjModel) -> SceneGeometry:
    """Draws the renderer's static arrays out of a compiled model."""
    visible = ~np.isin(model.geom_group, HIDDEN_GROUPS) & (model.geom_rgba[:, 3] > 0)
    unsupported = {T(t).name for t in model.geom_type[visible] if int(t) not in {int(p) for p in PRIMITIVES}}
    if unsupported:
        raise ValueError(f"the JAX renderer draws primitive geoms only; this model has {sorted(unsupported)}")
    groups = tuple((t, np.flatnonzero(visible & (model.geom_type == int(t))).astype(np.int32))
                   for t in PRIMITIVES if np.any(visible & (model.geom_type == int(t))))
    rgb = np.array(model.geom_rgba[:, :3], np.float32)
    has_mat = model.geom_matid >= 0
    rgb[has_mat] = model.mat_rgba[model.geom_matid[has_mat], :3]
    checker = np.zeros((model.ngeom, 2, 3), np.float32)
    cell = np.zeros((model.ngeom, 2), np.float32)
    for g in range(model.ngeom):
        checker[g], cell[g] = _checker_of(model, g)
    light_dir = np.array(model.light_dir, np.float32)
    light_dir /= np.maximum(np.linalg.norm(light_dir, axis=-1, keepdims=True), _EPS)
    extent = model.stat.extent
    return SceneGeometry(
        groups=groups,
        size=np.array(model.geom_size, np.float32),
        half_extent=np.array([_half_extent(int(model.geom_type[g]), model.geom_size[g]) for g in range(model.ngeom)],
                             np.float32),
        rgb=rgb, checker=checker, checker_cell=cell,
        fovy=np.array(model.cam_fovy, np.float32),
        cam_names=tuple(model.cam(i).name for i in range(model.ncam)),
        light_dir=light_dir, light_pos=np.array(model.light_pos, np.float32),
        light_diffuse=np.array(model.light_diffuse, np.float32),
        light_directional=np.asarray(model.light_type == mujoco.mjtLightType.mjLIGHT_DIRECTIONAL),
        light_shadow=np.asarray(model.light_castshadow, bool),
        head_ambient=np.array(model.vis.headlight.ambient, np.float32),
        head_diffuse=np.array(model.vis.headlight.diffuse, np.float32),
        znear=float(model.vis.map.znear * extent), zfar=float(model.vis.map.zfar * extent),
        colored=tuple(np.array([i for i in (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in names)
                                if i >= 0], np.int32) for names in S.COLORED_GEOMS),
        gtype=np.array(model.geom_type, np.int32),
    )


def episode_rgb(geo: SceneGeometry, colors: jax.Array) -> jax.Array:
    """Per-geom colours (B, ngeom, 3) with one episode's drawn colours (B, 4, 3) painted in."""
    colors = jnp.asarray(colors, jnp.float32)
    rgb = jnp.broadcast_to(jnp.asarray(geo.rgb), (colors.shape[0], geo.ngeom, 3))
    for row, ids in enumerate(geo.colored):
        rgb = rgb.at[:, ids].set(colors[:, row, None, :])
    return rgb


# ---- ray-primitive intersection: local frame, entry distance only, inf on a miss -------------------
# Vectors are tuples (x, y, z) of arrays: XLA:CPU vectorises these elementwise chains several times
# better than arrays with a trailing axis of 3. o, d: ray origin and unit direction in the geom's
# frame; s: the geom's size (three arrays).

def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _solve_entry(a, b, c):
    """Smaller root of a t^2 + 2 b t + c = 0 where the ray starts outside (c > 0), else inf."""
    disc = b * b - a * c
    t = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / a
    return jnp.where((disc >= 0) & (c > 0), t, _INF)


def _hit_plane(o, d, s):
    dz = jnp.where(d[2] < 0, d[2], -_EPS)
    t = -o[2] / dz
    x, y = o[0] + t * d[0], o[1] + t * d[1]
    inside = ((s[0] <= 0) | (jnp.abs(x) <= s[0])) & ((s[1] <= 0) | (jnp.abs(y) <= s[1]))
    return jnp.where((o[2] > 0) & (d[2] < 0) & inside, t, _INF)


def _hit_sphere(o, d, s):
    return _solve_entry(1.0, _dot(o, d), _dot(o, o) - s[0] * s[0])


def _hit_ellipsoid(o, d, s):
    os_, ds = tuple(o[i] / s[i] for i in range(3)), tuple(d[i] / s[i] for i in range(3))
    return _solve_entry(_dot(ds, ds), _dot(os_, ds), _dot(os_, os_) - 1.0)


def _hit_side(o, d, r, h):
    """Entry into the infinite z-cylinder of radius r, kept where |z| <= h."""
    a = d[0] * d[0] + d[1] * d[1]
    b = o[0] * d[0] + o[1] * d[1]
    c = o[0] * o[0] + o[1] * o[1] - r * r
    t = _solve_entry(jnp.maximum(a, _EPS), b, c)
    return jnp.where(jnp.abs(o[2] + t * d[2]) <= h, t, _INF)


def _hit_capsule(o, d, s):
    r, h = s[0], s[1]
    dz = o[2] - jnp.clip(o[2], -h, h)
    inside = o[0] * o[0] + o[1] * o[1] + dz * dz < r * r
    t = _hit_side(o, d, r, h)
    for sign in (-1.0, 1.0):
        oc = (o[0], o[1], o[2] - sign * h)
        t = jnp.minimum(t, _solve_entry(1.0, _dot(oc, d), _dot(oc, oc) - r * r))
    return jnp.where(inside, _INF, t)


def _hit_cylinder(o, d, s):
    r, h = s[0], s[1]
    t = _hit_side(o, d, r, h)
    dz = jnp.where(jnp.abs(d[2]) > _EPS, d[2], _EPS)
    for sign in (-1.0, 1.0):
        tc = (sign * h - o[2]) / dz
        x, y = o[0] + tc * d[0], o[1] + tc * d[1]
        ok = (sign * o[2] > h) & (tc > 0) & (x * x + y * y <= r * r)
        t = jnp.minimum(t, jnp.where(ok, tc, _INF))
    return t


def _hit_box(o, d, s):
    tnear, tfar = -_INF, _INF
    for i in range(3):
        inv = 1.0 / jnp.where(jnp.abs(d[i]) > _EPS, d[i], _EPS)
        a, b = (-s[i] - o[i]) * inv, (s[i] - o[i]) * inv
        tnear, tfar = jnp.maximum(tnear, jnp.minimum(a, b)), jnp.minimum(tfar, jnp.maximum(a, b))
    return jnp.where((tnear <= tfar) & (tnear > 0), tnear, _INF)


_HIT = {T.mjGEOM_PLANE: _hit_plane, T.mjGEOM_SPHERE: _hit_sphere, T.mjGEOM_CAPSULE: _hit_capsule,
        T.mjGEOM_ELLIPSOID: _hit_ellipsoid, T.mjGEOM_CYLINDER: _hit_cylinder, T.mjGEOM_BOX: _hit_box}


def _to_local(v, mat):
    """R^T v for v a tuple of 3 arrays and mat (..., 3, 3): a tuple of 3 arrays."""
    return tuple(v[0] * mat[..., 0, i] + v[1] * mat[..., 1, i] + v[2] * mat[..., 2, i] for i in range(3))


def _vdot(a, b):
    """Dot product over the last axis in full float32: `@` on GPUs defaults to TF32, whose 10-bit
    mantissa moves rays by a pixel and depth by a percent."""
    return jnp.sum(a * b, -1)


def _matvec(m, v):
    """m (3, 3) times each v (..., 3), in full float32."""
    return jnp.sum(m * v[..., None, :], -1)


def _split(x):
    """(..., 3) array -> tuple of 3 arrays."""
    return x[..., 0], x[..., 1], x[..., 2]


def _local_normal(gtype, p, s):
    """Outward normal (tuple of 3, not unit) at local surface point p of a primitive of type gtype."""
    zero, one = jnp.zeros_like(p[0]), jnp.ones_like(p[0])
    if gtype == T.mjGEOM_PLANE:
        return zero, zero, one
    if gtype == T.mjGEOM_SPHERE:
        return p
    if gtype == T.mjGEOM_ELLIPSOID:
        return tuple(p[i] / (s[i] * s[i]) for i in range(3))
    if gtype == T.mjGEOM_CAPSULE:
        return p[0], p[1], p[2] - jnp.clip(p[2], -s[1], s[1])
    if gtype == T.mjGEOM_CYLINDER:
        cap = jnp.abs(p[2]) >= s[1] * (1 - 1e-4)
        return jnp.where(cap, zero, p[0]), jnp.where(cap, zero, p[1]), jnp.where(cap, jnp.sign(p[2]), zero)
    # box: the face whose slab the point is closest to
    q = [jnp.abs(p[i]) / s[i] for i in range(3)]
    x_max = (q[0] >= q[1]) & (q[0] >= q[2])
    y_max = ~x_max & (q[1] >= q[2])
    z_max = ~x_max & ~y_max
    return tuple(jnp.where(m, jnp.sign(p[i]), zero) for i, m in enumerate((x_max, y_max, z_max)))


# ---- culling ----------------------------------------------------------------------------------

def _select(mask, priority, k):
    """Up to k indices (..., k) of True entries of mask (..., n), highest priority first."""
    k = min(k, mask.shape[-1])
    score = jnp.where(mask, priority, -_INF)
    top, idx = jax.lax.top_k(score, k)
    return idx, top > -_INF


_BOX_SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32)


def _corners(geo, ids, pos, mat):
    """Corners (n, 8, 3) in the world of the bounding boxes of geoms ids."""
    local = _BOX_SIGNS[None] * geo.half_extent[ids][:, None]  # (n, 8, 3), static
    m = mat[ids]
    return pos[ids][:, None] + jnp.sum(m[:, None] * local[:, :, None, :], -1)


def _overlaps(lo, hi, tlo, thi):
    """Whether 2-D rectangles lo/hi (n, 2) meet tile rectangles tlo/thi (nt, 2): (nt, n)."""
    return jnp.all((lo[None] <= thi[:, None]) & (hi[None] >= tlo[:, None]), -1)


# ---- the frame ---------------------------------------------------------------------------------

def _camera_rays(cfg: RenderConfig, fovy_deg, cam_mat):
    """Unit ray directions (H, W, 3) in the world, row 0 at the top, and the camera's axis (3,)."""
    h, w = cfg.height, cfg.width
    tan = jnp.tan(jnp.deg2rad(fovy_deg) / 2)
    y = (1 - 2 * (jnp.arange(h) + 0.5) / h) * tan
    x = (2 * (jnp.arange(w) + 0.5) / w - 1) * tan * (w / h)
    local = jnp.stack([jnp.broadcast_to(x[None], (h, w)), jnp.broadcast_to(y[:, None], (h, w)), -jnp.ones((h, w))], -1)
    local = local / jnp.linalg.norm(local, axis=-1, keepdims=True)
    return _matvec(cam_mat, local), -cam_mat[:, 2]


def _pack_min(t, k):
    """Min over the last axis of t (..., k) >= 0 and its index, from one integer reduction.

    Positive floats order like their bit patterns, so the slot index goes into the low mantissa
    bits (t loses at most 2^-17 of its value for k <= 64). inf comes back as _FAR."""
    bits = max(1, (k - 1).bit_length())
    low = (1 << bits) - 1
    key = jax.lax.bitcast_convert_type(jnp.minimum(t, _FAR), jnp.int32) & ~low | jnp.arange(k, dtype=jnp.int32)
    kmin = jnp.min(key, -1)
    return jax.lax.bitcast_convert_type(kmin & ~low, jnp.float32), kmin & low


def _closest(geo, origin, dirs, pos, mat, cand=None, t_min=None, any_hit=False, t_max=None):
    """Nearest entry along rays. origin (3,) shared or (R, 3) per ray; dirs (R, 3).

    cand: None (every visible geom) or {group index: ((1 or R, k) geom ids, (1 or R, k) valid)}.
    t_min: (R,) entries closer than this are clipped (the near plane; a clipped convex geom
      shows nothing, as its far side faces away).
    any_hit: only whether anything is hit (before t_max (R,), if given): returns (R,) bool.
    Returns t (R,) (>= _FAR on a miss) and geom id (R,) int32 (-1 on a miss).
    """
    best_t = jnp.full(dirs.shape[:1], _FAR)
    best_g = jnp.full(dirs.shape[:1], -1, jnp.int32)
    hit_any = jnp.zeros(dirs.shape[:1], bool)
    d = _split(dirs[:, None, :])
    o = _split(origin[None, None, :] if origin.ndim == 1 else origin[:, None, :])
    for gi, (gtype, ids) in enumerate(geo.groups):
        if cand is None or gi not in cand:
            g, ok = jnp.asarray(ids)[None, :], None  # (1, n)
        else:
            g, ok = cand[gi]
        p, m, s = pos[g], mat[g], jnp.asarray(geo.size)[g]
        rel = tuple(a - b for a, b in zip(o, _split(p)))
        t = _HIT[gtype](_to_local(rel, m), _to_local(d, m), _split(s))
        if ok is not None:
            t = jnp.where(ok, t, _INF)
        if t_min is not None:
            t = jnp.where(t >= t_min[:, None], t, _INF)
        if any_hit:
            hit_any = hit_any | jnp.any(t < (_INF if t_max is None else t_max[:, None]), -1)
            continue
        tj, j = _pack_min(t, t.shape[-1])
        gj = g[0][j] if g.shape[0] == 1 else jnp.take_along_axis(g, j[:, None], -1)[:, 0]
        closer = tj < best_t
        best_t = jnp.where(closer, tj, best_t)
        best_g = jnp.where(closer, gj, best_g)
    return hit_any if any_hit else (best_t, best_g)


def _occluded(geo, origins, dirs, pos, mat, cand=None, t_max=None):
    """Whether rays from origins (R, 3) along dirs (R, 3) hit a visible geom (before t_max (R,))."""
    return _closest(geo, origins, dirs, pos, mat, cand, any_hit=True, t_max=t_max)


def _surface_table(geo, pos, mat, geom_rgb):
    """Everything shading reads about each geom, one row per geom (ngeom, 27): one gather per pixel."""
    n = geo.ngeom
    return jnp.concatenate([
        pos, mat.reshape(n, 9), jnp.asarray(geo.size), jnp.asarray(geo.gtype, jnp.float32)[:, None], geom_rgb,
        jnp.asarray(geo.checker).reshape(n, 6), jnp.asarray(geo.checker_cell)], -1)


def _surface(geo, gid, hit, table):
    """Unit world normals, local points and colours (tuples of 3 arrays (R,)) at world points hit on geoms gid."""
    g = jnp.maximum(gid, 0)
    col = lambda a, b: tuple(table[:, c][g] for c in range(a, b))  # noqa: E731  (1-D gathers: fast on CPU)
    pos, m9, s, (gtype_of,) = col(0, 3), col(3, 12), col(12, 15), col(15, 16)
    rgb, checker, cell = col(16, 19), col(19, 25), col(25, 27)
    rel = tuple(hit[i] - pos[i] for i in range(3))
    p_loc = tuple(rel[0] * m9[i] + rel[1] * m9[3 + i] + rel[2] * m9[6 + i] for i in range(3))
    n_loc = (jnp.zeros_like(hit[0]),) * 3
    for gtype, _ in geo.groups:
        is_t = gtype_of == int(gtype)
        n_loc = tuple(jnp.where(is_t, a, b) for a, b in zip(_local_normal(gtype, p_loc, s), n_loc))
    n = tuple(m9[3 * i] * n_loc[0] + m9[3 * i + 1] * n_loc[1] + m9[3 * i + 2] * n_loc[2] for i in range(3))
    inv = jax.lax.rsqrt(jnp.maximum(_dot(n, n), _EPS))
    textured = cell[0] > 0
    parity = (jnp.floor(p_loc[0] / jnp.where(textured, cell[0], 1.0))
              + jnp.floor(p_loc[1] / jnp.where(textured, cell[1], 1.0))) % 2
    albedo = tuple(jnp.where(textured, jnp.where(parity > 0, checker[3 + i], checker[i]), rgb[i]) for i in range(3))
    return tuple(c * inv for c in n), albedo


def _toward_light(geo, i, hit):
    """Unit direction (tuple of 3) from hit points (tuple of 3) toward light i."""
    if geo.light_directional[i]:
        return tuple(jnp.full_like(hit[0], -geo.light_dir[i, k]) for k in range(3))
    v = tuple(geo.light_pos[i, k] - hit[k] for k in range(3))
    inv = jax.lax.rsqrt(jnp.maximum(_dot(v, v), _EPS))
    return tuple(c * inv for c in v)


def _tiles_of(x, cfg):
    """(H*W, ...) per-pixel array -> (ntiles, tile*tile, ...)."""
    h, w, t = cfg.height, cfg.width, cfg.tile
    x = x.reshape(h // t, t, w // t, t, *x.shape[1:])
    return jnp.moveaxis(x, 2, 1).reshape((h // t) * (w // t), t * t, *x.shape[4:])


def _untile(x, cfg):
    h, w, t = cfg.height, cfg.width, cfg.tile
    x = x.reshape(h // t, w // t, t, t, *x.shape[2:])
    return jnp.moveaxis(x, 2, 1).reshape(h * w, *x.shape[4:])


def _primary_candidates(geo, cfg, cam_pos, cam_mat, fovy_deg, pos, mat):
    """Per culled group: (nt, k) geom ids whose projected bounding box meets each tile, nearest first,
    and (nt, k) valid flags. A box that crosses the near plane is kept everywhere."""
    h, w, t = cfg.height, cfg.width, cfg.tile
    tan_y = jnp.tan(jnp.deg2rad(fovy_deg) / 2)
    tan_x = tan_y * (w / h)
    cols, rows = jnp.arange(w // t), jnp.arange(h // t)
    u0, u1 = -1 + 2 * cols * t / w, -1 + 2 * (cols + 1) * t / w
    v0, v1 = 1 - 2 * (rows + 1) * t / h, 1 - 2 * rows * t / h
    tlo = jnp.stack(jnp.broadcast_arrays(u0[None, :], v0[:, None]), -1).reshape(-1, 2)
    thi = jnp.stack(jnp.broadcast_arrays(u1[None, :], v1[:, None]), -1).reshape(-1, 2)
    cand = {}
    for gi, (gtype, ids) in enumerate(geo.groups):
        if gtype == T.mjGEOM_PLANE:
            continue
        rel = _corners(geo, ids, pos, mat) - cam_pos
        x, y, z = _vdot(rel, cam_mat[:, 0]), _vdot(rel, cam_mat[:, 1]), -_vdot(rel, cam_mat[:, 2])  # z: depth
        zs = jnp.maximum(z, geo.znear)
        u, v = x / zs / tan_x, y / zs / tan_y
        lo = jnp.stack([u.min(1), v.min(1)], -1)
        hi = jnp.stack([u.max(1), v.max(1)], -1)
        crosses = z.min(1) < geo.znear
        meets = _overlaps(lo, hi, tlo, thi) | crosses[None]
        meets = meets & (z.max(1) > geo.znear)[None]
        local, ok = _select(meets, jnp.broadcast_to(-z.min(1), meets.shape), cfg.max_per_tile)
        cand[gi] = (jnp.asarray(ids)[local], ok)
    return cand


def _shadow_candidates(geo, cfg, hit_tiles, lit_tiles, toward, pos, mat):
    """Per culled group: (nt, k) geoms whose bounding box, seen along a directional light (toward
    it: `toward`), meets the light-space rectangle of each tile's lit points, highest first."""
    a = jnp.where(jnp.abs(toward[2]) < 0.9, jnp.array([0.0, 0.0, 1.0]), jnp.array([1.0, 0.0, 0.0]))
    e1 = jnp.cross(toward, a)
    e1 = e1 / jnp.linalg.norm(e1)
    e2 = jnp.cross(toward, e1)
    big = 1e6
    proj = jnp.stack([_vdot(hit_tiles, e1), _vdot(hit_tiles, e2)], -1)  # (nt, P, 2)
    tlo = jnp.min(jnp.where(lit_tiles[..., None], proj, big), 1)
    thi = jnp.max(jnp.where(lit_tiles[..., None], proj, -big), 1)
    low = jnp.min(jnp.where(lit_tiles, _vdot(hit_tiles, toward), big), -1)  # lowest lit point along the light
    cand = {}
    for gi, (gtype, ids) in enumerate(geo.groups):
        if gtype == T.mjGEOM_PLANE:
            continue
        c = _corners(geo, ids, pos, mat)
        cp = jnp.stack([_vdot(c, e1), _vdot(c, e2)], -1)  # (n, 8, 2)
        height = _vdot(c, toward)
        meets = _overlaps(cp.min(1), cp.max(1), tlo, thi) & (height.max(1)[None] >= low[:, None])
        local, ok = _select(meets, jnp.broadcast_to(height.max(1), meets.shape), cfg.max_per_tile)
        cand[gi] = (jnp.asarray(ids)[local], ok)
    return cand


def _per_tile(fn, cand, *tiled):
    """Runs fn(*tile_args, tile_candidates) over tiles; candidates (nt, k) become (1, k) per tile."""
    return jax.vmap(lambda c, *args: fn(*args, {k: (g[None], ok[None]) for k, (g, ok) in c.items()}))(cand, *tiled)


def render_frame(geo: SceneGeometry, cfg: RenderConfig, geom_xpos, geom_xmat, cam_xpos, cam_xmat, geom_rgb):
    """One frame. geom_xpos (ngeom, 3), geom_xmat (ngeom, 3, 3), cam_xpos (3,), cam_xmat (3, 3),
    geom_rgb (ngeom, 3). Returns rgb (H, W, 3) uint8, depth (H, W) float32, geom id (H, W) int32."""
    cam = geo.cam_names.index(cfg.camera)
    dirs_hw, axis = _camera_rays(cfg, geo.fovy[cam], cam_xmat)
    dirs = dirs_hw.reshape(-1, 3)
    pos, mat = geom_xpos, geom_xmat
    cos_axis = _vdot(dirs, axis)
    t_min = geo.znear / cos_axis
    if cfg.tile:
        cand = _primary_candidates(geo, cfg, cam_xpos, cam_xmat, geo.fovy[cam], pos, mat)
        t, gid = _per_tile(lambda d, tmin, c: _closest(geo, cam_xpos, d, pos, mat, c, t_min=tmin), cand,
                           _tiles_of(dirs, cfg), _tiles_of(t_min, cfg))
        t, gid = _untile(t, cfg), _untile(gid, cfg)
    else:
        t, gid = _closest(geo, cam_xpos, dirs, pos, mat, t_min=t_min)
    depth = t * cos_axis
    keep = depth < geo.zfar
    gid = jnp.where(keep, gid, -1)
    depth = jnp.where(keep, depth, geo.zfar)
    t_hit = jnp.where(keep, t, 0.0)
    d = _split(dirs)
    hit = tuple(cam_xpos[i] + d[i] * t_hit for i in range(3))
    normal, albedo = _surface(geo, gid, hit, _surface_table(geo, pos, mat, geom_rgb))
    facing = _dot(normal, d)
    normal = tuple(jnp.where(facing > 0, -c, c) for c in normal)
    head = jnp.abs(facing)
    light = [geo.head_ambient[k] + geo.head_diffuse[k] * head for k in range(3)]
    origin = jnp.stack([hit[k] + normal[k] * 1e-3 for k in range(3)], -1)
    for i in range(len(geo.light_dir)):
        lam = jnp.maximum(_dot(normal, _toward_light(geo, i, hit)), 0.0)
        if cfg.shadows and geo.light_shadow[i]:
            lit = (lam > 0) & keep
            if cfg.tile and geo.light_directional[i]:
                toward = -jnp.asarray(geo.light_dir[i])
                o_t = _tiles_of(origin, cfg)
                c = _shadow_candidates(geo, cfg, o_t, _tiles_of(lit, cfg), toward, pos, mat)
                blocked = _untile(_per_tile(lambda o, cc: _occluded(geo, o, jnp.broadcast_to(toward, o.shape), pos, mat, cc),
                                            c, o_t), cfg)
            else:
                to_light = _toward_light(geo, i, hit)
                t_max = None if geo.light_directional[i] else jnp.sqrt(
                    sum((geo.light_pos[i, k] - hit[k]) ** 2 for k in range(3)))
                blocked = _occluded(geo, origin, jnp.stack(to_light, -1), pos, mat, t_max=t_max)
            lam = jnp.where(blocked, 0.0, lam)
        light = [light[k] + geo.light_diffuse[i, k] * lam for k in range(3)]
    bg = BACKGROUND_RGB
    rgb = jnp.stack([jnp.where(keep, albedo[k] * light[k], bg[k]) for k in range(3)], -1)
    rgb = jnp.clip(rgb * 255 + 0.5, 0, 255).astype(jnp.uint8)
    h, w = cfg.height, cfg.width
    return rgb.reshape(h, w, 3), depth.reshape(h, w), gid.reshape(h, w)


class Renderer:
    """Batched, jitted frames of one camera for one model.

    Example:
      r = Renderer(load_model(), RenderConfig(camera="head_cam"))
      out = r.render(poses, episode_rgb(r.geometry, colors))  # out["rgb"]: (B, 64, 64, 3) uint8
    """

    def __init__(self, model: mujoco.MjModel, cfg: RenderConfig = RenderConfig()):
        self.geometry = scene_geometry(model)
        if cfg.camera not in self.geometry.cam_names:
            raise ValueError(f"unknown camera {cfg.camera!r}; the model has {', '.join(self.geometry.cam_names)}")
        self.cfg = cfg
        self._cam = self.geometry.cam_names.index(cfg.camera)
        self._render = jax.jit(self.render_batch)

    def render_batch(self, poses: Poses, geom_rgb) -> dict:
        """Traceable: frames of the batch. geom_rgb (B, ngeom, 3) float32 in [0, 1].

        Returns {"rgb": (B, H, W, 3) uint8, "depth": (B, H, W) float32, "geom_id": (B, H, W) int32}.
        """
        c = self._cam
        one = functools.partial(render_frame, self.geometry, self.cfg)
        rgb, depth, gid = jax.vmap(one)(poses.geom_xpos, poses.geom_xmat, poses.cam_xpos[:, c], poses.cam_xmat[:, c],
                                        geom_rgb)
        return {"rgb": rgb, "depth": depth, "geom_id": gid}

    def render(self, poses: Poses, geom_rgb=None) -> dict:
        """Jitted `render_batch`; geom_rgb defaults to the model's colours."""
        if geom_rgb is None:
            geom_rgb = jnp.broadcast_to(jnp.asarray(self.geometry.rgb), (poses.geom_xpos.shape[0], self.geometry.ngeom, 3))
        return self._render(poses, geom_rgb)


@functools.lru_cache(maxsize=8)
def cached_renderers(size, cameras) -> tuple:
    """One Renderer of size x size pixels per camera named, in order; kept for the next call with the same
    arguments (cameras a tuple), so that their compiled programs are reused."""
    return tuple(Renderer(S.load_model(), RenderConfig(height=size, width=size, camera=c)) for c in cameras)


# ---- reprojection: a frame redrawn from another camera pose through its depth ---------------------

def rides_with_camera(model: mujoco.MjModel, camera: str = HEAD_CAMERA) -> np.ndarray:
    """(ngeom,) bool: the geoms of the body tree that carries `camera` (for the head camera, the robot's
    whole body, arms included), which `reproject` keeps where they were drawn rather than moving them
    with the world."""
    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if cam < 0:
        raise ValueError(f"unknown camera {camera!r}")
    root = model.body_rootid[model.cam_bodyid[cam]]
    if root == 0:  # a camera fixed in the world: nothing rides with it
        return np.zeros(model.ngeom, bool)
    return model.body_rootid[model.geom_bodyid] == root


def poses_of(model: mujoco.MjModel, qpos, mocap_pos) -> Poses:
    """Poses (B, ...) of states qpos (B, nq) with mocap_pos (B, nmocap, 3), by MuJoCo's C forward
    kinematics: where everything is at states no simulation reached (a predicted robot, for instance)."""
    out = kinematics(model, qpos, mocap_pos, ("geom_xpos", "geom_xmat", "cam_xpos", "cam_xmat"))
    return poses_from_arrays(*out.values())


def kinematics(model: mujoco.MjModel, qpos, mocap_pos, fields: tuple[str, ...]) -> dict[str, np.ndarray]:
    """MjData's `fields` (each (B, ...) stacked) after MuJoCo's C forward kinematics and camera placement at
    states qpos (B, nq) with mocap_pos (B, nmocap, 3), in the order of `fields`."""
    data = mujoco.MjData(model)
    out = {k: [] for k in fields}
    for q, mp in zip(np.asarray(qpos), np.asarray(mocap_pos)):
        data.qpos[:], data.mocap_pos[:] = q, mp
        mujoco.mj_kinematics(model, data)
        mujoco.mj_camlight(model, data)
        for k in out:
            out[k].append(getattr(data, k).copy())
    return {k: np.stack(v) for k, v in out.items()}


def camera_poses(model: mujoco.MjModel, qpos, mocap_pos, camera: str = HEAD_CAMERA) -> tuple[np.ndarray, np.ndarray]:
    """(B, 3) positions and (B, 3, 3) world-from-camera rotations of `camera` at states qpos (B, nq) with
    mocap_pos (B, nmocap, 3), by MuJoCo's C forward kinematics."""
    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if cam < 0:
        raise ValueError(f"unknown camera {camera!r}")
    k = kinematics(model, qpos, mocap_pos, ("cam_xpos", "cam_xmat"))
    return k["cam_xpos"][:, cam].astype(np.float32), k["cam_xmat"][:, cam].reshape(-1, 3, 3).astype(np.float32)


def project_points(points, cam_pos, cam_mat, fovy_deg) -> np.ndarray:
    """(B, K, 2) float32 image coordinates in [0, 1] (x right, y down, as a frame's columns and rows; pixel
    (i, j) of an S x S frame is centred at ((j + 0.5) / S, (i + 0.5) / S), pixel_rays' rays) of world points
    (B, K, 3) seen by square-frame cameras at cam_pos (B, 3) with world-from-camera rotations cam_mat (B, 3, 3)
    and a vertical field of view of fovy_deg; NaN for a point at or behind the camera's plane. Outside
    [0, 1]: in front of the camera but out of its view."""
    rel = np.asarray(points, np.float64) - np.asarray(cam_pos, np.float64)[:, None]
    local = np.einsum("bij,bki->bkj", np.asarray(cam_mat, np.float64), rel)  # camera frame: R^T (p - c)
    depth = -local[..., 2]
    tan = np.tan(np.deg2rad(float(fovy_deg)) / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([(local[..., 0] / depth / tan + 1) / 2, (1 - local[..., 1] / depth / tan) / 2], -1)
    return np.where((depth > 1e-6)[..., None], uv, np.nan).astype(np.float32)


def grip_pixels(model: mujoco.MjModel, qpos, mocap_pos, camera: str = HEAD_CAMERA) -> np.ndarray:
    """(B, 2, 2) float32: where the left and right hands' grip sites (SceneIndex.grip_site) appear in `camera`'s
    square frame at states qpos (B, nq) with mocap_pos (B, nmocap, 3), as project_points' image
    coordinates (NaN behind the camera), by MuJoCo's C forward kinematics."""
    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if cam < 0:
        raise ValueError(f"unknown camera {camera!r}")
    k = kinematics(model, qpos, mocap_pos, ("site_xpos", "cam_xpos", "cam_xmat"))
    sites = np.asarray(S.scene_index(model).grip_site)
    return project_points(k["site_xpos"][:, sites], k["cam_xpos"][:, cam], k["cam_xmat"][:, cam].reshape(-1, 3, 3),
                          model.cam_fovy[cam])


def riding_pixels(rides, geom_id) -> np.ndarray:
    """(B, H, W) bool: the pixels of a drawing (geom_id (B, H, W), the renderer's; -1 where nothing was
    hit) whose geom rides with the camera (rides: rides_with_camera's (ngeom,) mask)."""
    gid = np.asarray(geom_id)
    return np.asarray(rides)[np.clip(gid, 0, None)] & (gid >= 0)


def _fill_holes(img, filled, passes: int) -> tuple[jax.Array, jax.Array]:
    """Each hole takes the mean of its filled 3x3 neighbours, `passes` rings inwards; (B, H, W, 3) float,
    (B, H, W) bool -> the same, updated."""
    h, w = filled.shape[1:]
    for _ in range(passes):
        pi = jnp.pad(img * filled[..., None], ((0, 0), (1, 1), (1, 1), (0, 0)))
        pm = jnp.pad(filled.astype(img.dtype), ((0, 0), (1, 1), (1, 1)))
        acc = sum(pi[:, dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
        n = sum(pm[:, dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
        grow = ~filled & (n > 0)
        img = jnp.where(grow[..., None], acc / jnp.maximum(n, 1)[..., None], img)
        filled = filled | grow
    return img, filled


def pixel_rays(h: int, w: int, fovy_deg) -> jax.Array:
    """(H, W, 3) float32: each pixel's ray through its centre in the camera's frame (MuJoCo's: x right,
    y up, looking down -z), scaled so that its depth along the axis is 1. Traceable in fovy_deg."""
    tan = jnp.tan(jnp.deg2rad(jnp.asarray(fovy_deg, jnp.float32)) / 2)
    ys = (1 - 2 * (jnp.arange(h, dtype=jnp.float32) + 0.5) / h) * tan
    xs = (2 * (jnp.arange(w, dtype=jnp.float32) + 0.5) / w - 1) * tan * (w / h)
    return jnp.stack(jnp.broadcast_arrays(xs[None], ys[:, None], -jnp.ones((h, w), jnp.float32)), -1)


@functools.partial(jax.jit, static_argnums=(3, 4))
def floor_hits(cam_pos, cam_mat, fovy_deg, h: int, w: int) -> tuple[jax.Array, jax.Array]:
    """Where each pixel's ray meets the floor (the plane z = 0), for cameras at cam_pos (B, 3) with
    world-from-camera cam_mat (B, 3, 3): (B, H, W, 2) world x, y in metres (zero where the ray does not
    come down to the floor) and (B, H, W, 3) the ray's unit direction in the world, float32. The
    geometry a generator needs to draw the floor that a frame never showed."""
    pos, mat = jnp.asarray(cam_pos, jnp.float32), jnp.asarray(cam_mat, jnp.float32)
    ray = jnp.einsum("bij,hwj->bhwi", mat, pixel_rays(h, w, fovy_deg))
    ray /= jnp.linalg.norm(ray, axis=-1, keepdims=True)
    down = ray[..., 2] < -1e-6
    dist = jnp.where(down, pos[:, None, None, 2] / jnp.where(down, -ray[..., 2], 1.0), 0.0)
    xy = jnp.where(down[..., None], pos[:, None, None, :2] + dist[..., None] * ray[..., :2], 0.0)
    return xy, ray


@functools.partial(jax.jit, static_argnames=("fill", "keep_rides"))
def reproject(rgb, depth, rides, cam_pos0, cam_mat0, cam_pos, cam_mat, fovy_deg, fill: int = 8,
              keep_rides: bool = True):
    """Frames redrawn at new camera poses from frames drawn at others, through their depth: each pixel's
    point is carried into the new camera (the nearest wins a pixel; of equally near ones, the first in
    the frame's row-major order) and the pixels that nothing lands on take their neighbours' colour
    (`fill` rings), the rest the frame's mean. Pixels that ride with the camera stay where they were
    (keep_rides), or are left out, for a drawing of the camera's carrier at its new pose to take their
    place. What an imagination that moves the camera over a still scene can show at best from one
    frame: parallax right, new views of what the frame hid only guessed. Traceable (under jit, scan).

    rgb (B, H, W, 3) uint8; depth (B, H, W) float metres along the camera axis (the renderer's);
    rides (B, H, W) bool; cam_pos0, cam_pos (B, 3) and cam_mat0, cam_mat (B, 3, 3) world-from-camera
    (MuJoCo's cam_xpos, cam_xmat); fovy_deg: the camera's vertical field of view.
    Returns (B, H, W, 3) uint8 frames and (B, H, W) bool: the pixels a point landed on."""
    f32 = jnp.float32
    depth, rides = jnp.asarray(depth, f32), jnp.asarray(rides, bool)
    b, h, w = depth.shape
    n = b * h * w
    tan = jnp.tan(jnp.deg2rad(jnp.asarray(fovy_deg, f32)) / 2)
    local = pixel_rays(h, w, fovy_deg)[None] * depth[..., None]
    world = jnp.asarray(cam_pos0, f32)[:, None, None] + jnp.einsum("bij,bhwj->bhwi", jnp.asarray(cam_mat0, f32), local)
    new = jnp.einsum("bji,bhwj->bhwi", jnp.asarray(cam_mat, f32), world - jnp.asarray(cam_pos, f32)[:, None, None])
    z = -new[..., 2]
    zs = jnp.maximum(z, 1e-6)
    # clipped to one pixel past each edge before the cast: a point far off the axis must not overflow
    col = jnp.round(jnp.clip((new[..., 0] / zs / (tan * w / h) + 1) * w / 2 - 0.5, -1, w)).astype(jnp.int32)
    row = jnp.round(jnp.clip((1 - new[..., 1] / zs / tan) * h / 2 - 0.5, -1, h)).astype(jnp.int32)
    rr = jnp.broadcast_to(jnp.arange(h)[None, :, None], (b, h, w))
    cc = jnp.broadcast_to(jnp.arange(w)[None, None], (b, h, w))
    row, col, z = jnp.where(rides, rr, row), jnp.where(rides, cc, col), jnp.where(rides, 0.0, z)
    ok = ((z > 1e-3) | rides) & (col >= 0) & (col < w) & (row >= 0) & (row < h) & (keep_rides | ~rides)
    bb = jnp.broadcast_to(jnp.arange(b)[:, None, None], (b, h, w))
    target = jnp.where(ok, (bb * h + row) * w + col, n).ravel()  # n: dropped by the scatters
    z = z.ravel()
    nearest = jnp.full(n, jnp.inf, f32).at[target].min(z, mode="drop")
    wins = ok.ravel() & (z == nearest[jnp.minimum(target, n - 1)])
    winner = jnp.full(n, n, jnp.int32).at[target].min(jnp.where(wins, jnp.arange(n, dtype=jnp.int32), n), mode="drop")
    covered = winner < n
    colours = jnp.asarray(rgb).reshape(n, 3).astype(f32)
    img = jnp.where(covered[:, None], colours[jnp.minimum(winner, n - 1)], 0.0).reshape(b, h, w, 3)
    covered = covered.reshape(b, h, w)
    img, filled = _fill_holes(img, covered, fill)
    mean = colours.reshape(b, -1, 3).mean(axis=1)[:, None, None]
    img = jnp.where(filled[..., None], img, mean)
    return jnp.clip(img + 0.5, 0, 255).astype(jnp.uint8), covered
