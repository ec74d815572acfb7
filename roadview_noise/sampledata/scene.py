"""Procedural road scene for the synthetic "ideal drive": open3d triangle meshes with per-material albedo, LiDAR
reflectivity and radar RCS, ray-cast with ``open3d.t.geometry.RaycastingScene``.

World frame (ISO 8855): x along the road, y to the left, z up, origin on the road surface at the ego start. The road
is two 3.5 m lanes (right lane y ∈ [−3.5, 0], driving on the right) plus a 3.5 m parking strip each side, kerbs at
|y| = 7 m (0.15 m high), pavement beyond, building facades in the plane |y| = 14 m. Objects are axis-aligned; moving
objects translate with a constant velocity, so the scene at time t is the scene at 0 shifted per object.
The layout (colours, positions, building sizes) is drawn from ``derive_rng(seed, "sampledata", "scene")``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import open3d as o3d

from ..seeding import derive_rng

# ---------------------------------------------------------------------------------------------------------------
# Materials


@dataclass(frozen=True)
class Material:
    """Diffuse linear-RGB albedo, Lambertian near-infrared reflectivity ρ (865–903 nm) and the radar cross-section
    of one scattering centre on this material (dBsm, 77 GHz). ``pattern`` adds procedural texture."""

    name: str
    albedo_rgb: tuple[float, float, float]
    nir_reflectivity: float
    rcs_dbsm: float
    pattern: str = "plain"          # one of PATTERNS


PATTERNS = ("plain", "asphalt", "paving", "facade")


GLASS = Material("glass", (0.04, 0.05, 0.06), 0.05, 5.0)
MATERIALS: tuple[Material, ...] = (
    Material("asphalt", (0.075, 0.075, 0.08), 0.12, -20.0, "asphalt"),
    Material("marking", (0.75, 0.75, 0.72), 0.65, -20.0),
    Material("pavement", (0.30, 0.29, 0.27), 0.30, -20.0, "paving"),
    Material("kerb", (0.45, 0.44, 0.42), 0.40, -10.0),
    Material("brick", (0.33, 0.11, 0.07), 0.45, 5.0, "facade"),
    Material("render_beige", (0.55, 0.47, 0.35), 0.55, 5.0, "facade"),
    Material("concrete_grey", (0.33, 0.33, 0.34), 0.35, 5.0, "facade"),
    Material("render_white", (0.70, 0.70, 0.68), 0.60, 5.0, "facade"),
    Material("roof", (0.12, 0.10, 0.10), 0.15, 0.0),
    Material("paint_red", (0.45, 0.03, 0.03), 0.45, 10.0),
    Material("paint_white", (0.75, 0.75, 0.75), 0.80, 10.0),
    Material("paint_black", (0.03, 0.03, 0.035), 0.06, 10.0),
    Material("paint_silver", (0.45, 0.46, 0.48), 0.55, 10.0),
    Material("paint_blue", (0.04, 0.08, 0.35), 0.30, 10.0),
    Material("paint_yellow", (0.70, 0.50, 0.04), 0.70, 10.0),
    Material("car_glass", (0.03, 0.035, 0.04), 0.08, 10.0),
    Material("tyre", (0.02, 0.02, 0.02), 0.04, 10.0),
    Material("jacket", (0.40, 0.10, 0.08), 0.40, -8.0),
    Material("jeans", (0.08, 0.11, 0.25), 0.30, -8.0),
    Material("skin", (0.50, 0.35, 0.25), 0.35, -8.0),
    Material("bike_frame", (0.30, 0.30, 0.32), 0.30, -3.0),
    Material("pole", (0.25, 0.25, 0.27), 0.30, 3.0),
    Material("sign_face", (0.60, 0.05, 0.05), 0.90, 8.0),
    GLASS,
)
MAT = {m.name: i for i, m in enumerate(MATERIALS)}
CAR_PAINTS = ("paint_red", "paint_white", "paint_black", "paint_silver", "paint_blue", "paint_yellow")
FACADES = ("brick", "render_beige", "concrete_grey", "render_white")

ROAD_HALF_WIDTH_M = 7.0
KERB_HEIGHT_M = 0.15
FACADE_Y_M = 14.0
LANE_CENTRE_Y_M = -1.75

# ---------------------------------------------------------------------------------------------------------------
# Mesh building


@dataclass(frozen=True)
class Part:
    vertices_m: np.ndarray         # (V, 3) float64
    triangles: np.ndarray          # (T, 3) int64
    material: int


def box(lo, hi, material: str) -> Part:
    """Axis-aligned box from corner ``lo`` to corner ``hi`` (m); outward-facing triangles."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[hi[0] if i & 1 else lo[0], hi[1] if i & 2 else lo[1], hi[2] if i & 4 else lo[2]]
                  for i in range(8)])
    t = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                  [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    return Part(v, t, MAT[material])


def quad_z(x0, x1, y0, y1, z, material: str) -> Part:
    """Horizontal rectangle at height z facing up."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)
    return Part(v, np.array([[0, 1, 2], [0, 2, 3]]), MAT[material])


def quad_y(x0, x1, z0, z1, y, material: str) -> Part:
    """Vertical rectangle in the plane y = const."""
    v = np.array([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]], float)
    return Part(v, np.array([[0, 1, 2], [0, 2, 3]]), MAT[material])


@dataclass(frozen=True)
class SceneObject:
    """A rigid object: merged parts (world coordinates at t = 0), constant velocity, semantic class, and how many
    radar scattering centres to sample on its surface."""

    name: str
    kind: str
    vertices_m: np.ndarray
    triangles: np.ndarray
    triangle_material: np.ndarray
    velocity_m_per_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radar_centres: int = 0

    @classmethod
    def from_parts(cls, name: str, kind: str, parts: list[Part], **kw) -> "SceneObject":
        offs = np.cumsum([0] + [len(p.vertices_m) for p in parts[:-1]])
        return cls(name, kind, np.concatenate([p.vertices_m for p in parts]),
                   np.concatenate([p.triangles + o for p, o in zip(parts, offs)]),
                   np.concatenate([np.full(len(p.triangles), p.material) for p in parts]), **kw)

    def vertices_at(self, t_s: float) -> np.ndarray:
        return self.vertices_m + t_s * np.asarray(self.velocity_m_per_s)


def vehicle(name: str, x: float, y: float, paint: str, length=4.5, width=1.8, height=1.45, van=False,
            velocity=(0.0, 0.0, 0.0)) -> SceneObject:
    """Car (or van): body box, glazed cabin, four wheels; (x, y) is the centre of the footprint."""
    hl, hw = length / 2, width / 2
    body_top = 0.55 * height if not van else 0.45 * height
    cab_lo = (x - 0.30 * length, y - hw + 0.08) if not van else (x - hl + 0.1, y - hw + 0.05)
    cab_hi = (x + 0.20 * length, y + hw - 0.08) if not van else (x + 0.30 * length, y + hw - 0.05)
    parts = [box((x - hl, y - hw, 0.30), (x + hl, y + hw, body_top), paint),
             box((*cab_lo, body_top), (*cab_hi, height), "car_glass" if not van else paint),
             box((cab_lo[0] + 0.15, cab_lo[1] - 0.01, height - 0.06),                # roof panel
                 (cab_hi[0] - 0.15, cab_hi[1] + 0.01, height + 0.01), paint)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = x + sx * (hl - 0.8), y + sy * (hw - 0.10)           # tyres stand 2 cm proud of the body
            parts.append(box((cx - 0.33, cy - 0.12, 0.0), (cx + 0.33, cy + 0.12, 0.62), "tyre"))
    if van:                                              # glazed band round the upper cabin
        parts.append(box((cab_lo[0] - 0.01, cab_lo[1] - 0.01, body_top + 0.35 * (height - body_top)),
                         (cab_hi[0] + 0.01, cab_hi[1] + 0.01, body_top + 0.8 * (height - body_top)), "car_glass"))
    return SceneObject.from_parts(name, "vehicle", parts, velocity_m_per_s=velocity, radar_centres=16)


def pedestrian(name: str, x: float, y: float, z: float = 0.0, velocity=(0.0, 0.0, 0.0)) -> SceneObject:
    """A 1.75 m person standing at height z (the pavement is at the kerb height)."""
    parts = [box((x - 0.10, y - 0.18, z), (x + 0.10, y - 0.02, z + 0.85), "jeans"),
             box((x - 0.10, y + 0.02, z), (x + 0.10, y + 0.18, z + 0.85), "jeans"),
             box((x - 0.13, y - 0.23, z + 0.85), (x + 0.13, y + 0.23, z + 1.50), "jacket"),
             box((x - 0.10, y - 0.09, z + 1.52), (x + 0.10, y + 0.09, z + 1.75), "skin")]
    return SceneObject.from_parts(name, "pedestrian", parts, velocity_m_per_s=velocity, radar_centres=4)


def cyclist(name: str, x: float, y: float, velocity=(0.0, 0.0, 0.0)) -> SceneObject:
    parts = [box((x - 0.85, y - 0.02, 0.0), (x - 0.20, y + 0.02, 0.68), "tyre"),
             box((x + 0.20, y - 0.02, 0.0), (x + 0.85, y + 0.02, 0.68), "tyre"),
             box((x - 0.55, y - 0.03, 0.40), (x + 0.55, y + 0.03, 0.75), "bike_frame"),
             box((x - 0.30, y - 0.15, 0.75), (x - 0.05, y + 0.15, 1.00), "jeans"),
             box((x - 0.25, y - 0.20, 1.00), (x + 0.15, y + 0.20, 1.55), "jacket"),
             box((x - 0.08, y - 0.09, 1.55), (x + 0.10, y + 0.09, 1.78), "skin")]
    return SceneObject.from_parts(name, "cyclist", parts, velocity_m_per_s=velocity, radar_centres=6)


def street_lamp(name: str, x: float, side: int) -> SceneObject:
    """Pole at |y| = 8 m with an arm towards the road; ``side`` +1 left, −1 right."""
    y = side * 8.0
    parts = [box((x - 0.08, y - 0.08, KERB_HEIGHT_M), (x + 0.08, y + 0.08, 7.0), "pole"),
             box((x - 0.06, min(y, y - side * 1.5), 6.85), (x + 0.06, max(y, y - side * 1.5), 7.0), "pole")]
    return SceneObject.from_parts(name, "pole", parts, radar_centres=3)


def sign(name: str, x: float, y: float) -> SceneObject:
    """Traffic sign facing −x (towards the ego): pole plus a 0.8 m plate, retro-reflective face."""
    parts = [box((x - 0.04, y - 0.04, KERB_HEIGHT_M), (x + 0.04, y + 0.04, 2.2), "pole"),
             box((x - 0.01, y - 0.4, 2.2), (x + 0.01, y + 0.4, 3.0), "pole"),
             Part(np.array([[x - 0.012, y - 0.4, 2.2], [x - 0.012, y + 0.4, 2.2], [x - 0.012, y + 0.4, 3.0],
                            [x - 0.012, y - 0.4, 3.0]]), np.array([[0, 1, 2], [0, 2, 3]]), MAT["sign_face"])]
    return SceneObject.from_parts(name, "sign", parts, radar_centres=4)


@dataclass(frozen=True)
class Building:
    """A box building whose street facade lies in the plane y = ``side`` · FACADE_Y_M."""

    x0_m: float
    x1_m: float
    height_m: float
    side: int
    material: str


def building_object(name: str, b: Building) -> SceneObject:
    y0 = b.side * FACADE_Y_M
    y1 = b.side * (FACADE_Y_M + 12.0)
    lo, hi = (b.x0_m, min(y0, y1), 0.0), (b.x1_m, max(y0, y1), b.height_m)
    walls = box(lo, hi, b.material)
    mat = np.full(12, walls.material)
    mat[[2, 3]] = MAT["roof"]                               # triangles 2, 3 of box() are the top face
    area = (b.x1_m - b.x0_m) * b.height_m
    return SceneObject(name, "building", walls.vertices_m, walls.triangles, mat,
                       radar_centres=int(area / 4.0))


def road_parts(x0: float, x1: float) -> list[Part]:
    """Asphalt, kerbs, pavement and lane markings (markings 5 mm above the asphalt)."""
    w, k = ROAD_HALF_WIDTH_M, KERB_HEIGHT_M
    parts = [quad_z(x0, x1, -w, w, 0.0, "asphalt"),
             quad_z(x0, x1, w, 60.0, k, "pavement"), quad_z(x0, x1, -60.0, -w, k, "pavement"),
             quad_y(x0, x1, 0.0, k, -w, "kerb"),
             Part(np.array([[x0, w, 0.0], [x0, w, k], [x1, w, k], [x1, w, 0.0]]), np.array([[0, 1, 2], [0, 2, 3]]),
                  MAT["kerb"])]
    for y in (-3.5, 3.5):                                           # solid lines: lanes | parking strips
        parts.append(quad_z(x0, x1, y - 0.075, y + 0.075, 0.005, "marking"))
    for xs in np.arange(-100.0, 600.0, 9.0):                         # dashed centre line: 3 m dash, 6 m gap
        parts.append(quad_z(xs, xs + 3.0, -0.075, 0.075, 0.005, "marking"))
    return parts


# ---------------------------------------------------------------------------------------------------------------
# Scene


@dataclass(frozen=True)
class Scene:
    """The static layout and the moving objects of one sequence, plus the ego trajectory."""

    objects: tuple[SceneObject, ...]
    buildings: tuple[Building, ...]
    ego_start_m: tuple[float, float, float] = (0.0, LANE_CENTRE_Y_M, 0.0)
    ego_velocity_m_per_s: tuple[float, float, float] = (15.0, 0.0, 0.0)
    frame_interval_s: float = 0.2
    sun_elevation_deg: float = 40.0
    sun_azimuth_deg: float = 150.0          # from +x towards +y: behind-left of the ego; right facades sunlit

    @property
    def sun_direction(self) -> np.ndarray:
        """Unit vector towards the sun (world frame)."""
        e, a = np.radians(self.sun_elevation_deg), np.radians(self.sun_azimuth_deg)
        return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])

    def frame_time_s(self, frame: int) -> float:
        return frame * self.frame_interval_s

    def ego_position_m(self, t_s: float) -> np.ndarray:
        """Ego reference point (ground under the rear axle) at time t; the ego drives straight along +x."""
        return np.asarray(self.ego_start_m) + t_s * np.asarray(self.ego_velocity_m_per_s)

    def snapshot(self, t_s: float) -> "Snapshot":
        return Snapshot(self, t_s)


def build_scene(seed: int) -> Scene:
    """The sample-drive scene; deterministic for a seed (layout, colours, building sizes)."""
    rng = derive_rng(seed, "sampledata", "scene")
    objs = [SceneObject.from_parts("road", "road", road_parts(-200.0, 2000.0))]
    buildings = []
    for side in (1, -1):
        x = -120.0 + rng.uniform(0, 5)
        while x < 420.0:
            length = float(rng.uniform(12.0, 35.0))
            buildings.append(Building(float(x), float(x + length), float(rng.uniform(9.0, 22.0)), side,
                                      str(rng.choice(FACADES))))
            x += length + float(rng.choice([0.0, 0.0, rng.uniform(2.0, 6.0)]))
    objs += [building_object(f"building_{i}", b) for i, b in enumerate(buildings)]
    for side in (1, -1):
        for i, x in enumerate(np.arange(-100.0, 420.0, 25.0) + (12.5 if side > 0 else 0.0)):
            objs.append(street_lamp(f"lamp_{'lr'[side < 0]}{i}", float(x), side))
    objs.append(sign("sign_0", 40.0 + float(rng.uniform(-3, 3)), -7.6))
    paints = rng.permutation(CAR_PAINTS)
    objs += [vehicle("lead_car", 22.0 + float(rng.uniform(-2, 2)), LANE_CENTRE_Y_M, paints[0], velocity=(12.0, 0, 0)),
             vehicle("oncoming_car", 70.0 + float(rng.uniform(-5, 5)), -LANE_CENTRE_Y_M, paints[1],
                     velocity=(-12.0, 0, 0)),
             vehicle("parked_van", 12.0 + float(rng.uniform(-2, 2)), -5.2, paints[2], length=5.2, width=2.0,
                     height=2.2, van=True),
             vehicle("parked_car_r1", 33.0 + float(rng.uniform(-2, 2)), -5.2, paints[3]),
             vehicle("parked_car_l0", 28.0 + float(rng.uniform(-2, 2)), 5.2, paints[4]),
             vehicle("parked_car_l1", 58.0 + float(rng.uniform(-3, 3)), 5.2, paints[5]),
             pedestrian("pedestrian", 30.0 + float(rng.uniform(-3, 3)), -9.5, KERB_HEIGHT_M, velocity=(1.4, 0, 0)),
             cyclist("cyclist", 42.0 + float(rng.uniform(-3, 3)), -3.0, velocity=(5.0, 0, 0))]
    return Scene(tuple(objs), tuple(buildings))


# ---------------------------------------------------------------------------------------------------------------
# Ray casting


@dataclass(frozen=True)
class Hits:
    """First intersections of a batch of rays (world frame): range t (inf: no hit), unit normal facing the ray
    origin, material index and object index (−1: no hit)."""

    t_m: np.ndarray
    normal: np.ndarray
    material: np.ndarray
    object_index: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.t_m)


class Snapshot:
    """The scene at time t as one ``RaycastingScene`` (one geometry per object)."""

    def __init__(self, scene: Scene, t_s: float):
        self.scene, self.t_s = scene, t_s
        self._rc = o3d.t.geometry.RaycastingScene()
        self._tri_offset = np.zeros(len(scene.objects) + 1, dtype=np.int64)
        for i, obj in enumerate(scene.objects):
            mesh = o3d.t.geometry.TriangleMesh()
            mesh.vertex.positions = o3d.core.Tensor(obj.vertices_at(t_s).astype(np.float32))
            mesh.triangle.indices = o3d.core.Tensor(obj.triangles.astype(np.int32))
            if self._rc.add_triangles(mesh) != i:          # geometry ids are assigned 0, 1, 2, … in order
                raise RuntimeError("unexpected open3d geometry id")
            self._tri_offset[i + 1] = self._tri_offset[i] + len(obj.triangles)
        self._tri_material = np.concatenate([o.triangle_material for o in scene.objects]).astype(np.int16)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """Cast rays (unit ``directions``; origins broadcast); one vectorised call."""
        origins = np.broadcast_to(origins, directions.shape)
        rays = np.concatenate([origins, directions], axis=-1).astype(np.float32)
        ans = self._rc.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        gid = ans["geometry_ids"].numpy()
        hit = np.isfinite(t)
        obj = np.where(hit, gid, 0).astype(np.int64)
        prim = np.where(hit, ans["primitive_ids"].numpy(), 0).astype(np.int64)
        normal = ans["primitive_normals"].numpy().astype(np.float64)     # unit length (zero where no hit)
        flip = np.sum(normal * directions, axis=-1, keepdims=True) > 0
        normal = np.where(flip, -normal, normal)
        material = np.where(hit, self._tri_material[self._tri_offset[obj] + prim], -1)
        return Hits(t, normal, material, np.where(hit, obj, -1))

    def occluded(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Whether each ray hits anything (shadow test)."""
        rays = np.concatenate([origins, np.broadcast_to(directions, origins.shape)], axis=-1).astype(np.float32)
        return self._rc.test_occlusions(o3d.core.Tensor(rays)).numpy()

    @cached_property
    def velocities_m_per_s(self) -> np.ndarray:
        return np.array([o.velocity_m_per_s for o in self.scene.objects], dtype=np.float64)


# ---------------------------------------------------------------------------------------------------------------
# Surface properties with procedural texture


def _hash01(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer cell (integer hash, no RNG state)."""
    h = (i.astype(np.int64) * 73856093) ^ (j.astype(np.int64) * 19349663)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF).astype(np.float64) / 65536.0


def surface_properties(points_m: np.ndarray, hits: Hits) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB albedo (N, 3) and NIR reflectivity (N,) at world hit points (no-hit rows are zero).

    Textures: asphalt (5 cm grain, ±8 %) and paving (0.6 m slabs, ±10 %) get cell noise; facades get a grid of
    glazed windows (3 m bays, 3.2 m storeys, above 1.5 m), glass for camera and LiDAR alike."""
    albedo_table = np.array([m.albedo_rgb for m in MATERIALS] + [(0.0, 0.0, 0.0)])
    nir_table = np.array([m.nir_reflectivity for m in MATERIALS] + [0.0])
    mat = np.where(hits.material >= 0, hits.material, len(MATERIALS))
    albedo = albedo_table[mat]
    nir = nir_table[mat]
    pattern = np.array([PATTERNS.index(m.pattern) for m in MATERIALS] + [0])[mat]
    x, y, z = points_m[..., 0], points_m[..., 1], points_m[..., 2]

    rough = pattern == PATTERNS.index("asphalt")
    if rough.any():
        g = 1.0 + 0.16 * (_hash01(np.floor(x[rough] / 0.05), np.floor(y[rough] / 0.05)) - 0.5)
        albedo[rough] *= g[:, None]
    paving = pattern == PATTERNS.index("paving")
    if paving.any():
        g = 1.0 + 0.2 * (_hash01(np.floor(x[paving] / 0.6), np.floor(y[paving] / 0.6)) - 0.5)
        albedo[paving] *= g[:, None]
    facade = pattern == PATTERNS.index("facade")
    if facade.any():
        n = hits.normal[facade]
        along = np.where(np.abs(n[:, 1]) > 0.5, x[facade], y[facade])   # horizontal coordinate in the wall
        zz = z[facade]
        bay = np.mod(along, 3.0) / 3.0
        storey = np.mod(zz - 1.5, 3.2) / 3.2
        window = (bay > 0.25) & (bay < 0.75) & (storey > 0.25) & (storey < 0.75) & (zz > 1.5) & (np.abs(n[:, 2]) < 0.5)
        idx = np.flatnonzero(facade)[window]
        albedo[idx] = GLASS.albedo_rgb
        nir[idx] = GLASS.nir_reflectivity
    return albedo, nir
