"""The cell's look: the table's top, the objects' surfaces and the room behind them,
projected from the walk's frames, so that the twin seen from a frame's pose resembles
that frame (the paper's twin is photo-realistic).

Every fifth registered frame is held out of the projection, to judge the result
(:mod:`twinrl_sim.reconstruct.look_score`). Frames are first undistorted into an ideal
pinhole with its principal point at the centre, the camera a MuJoCo render has.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pycolmap
import xatlas
from PIL import Image

from twinrl_sim.cubemap import cube_directions
from twinrl_sim.reconstruct.align import Similarity
from twinrl_sim.reconstruct.objects import TwinObject
from twinrl_sim.reconstruct.segment import TablePlane
from twinrl_sim.reconstruct.sfm import SparseModel

HELD_OUT_EVERY = 5  # every fifth registered frame judges the look instead of painting it
MAX_WIDTH = 640  # px: frames are painted from and judged at this width at most
MAX_PAINTERS = 40  # frames (evenly spread) that paint: more only blur and cost time
TABLE_TEXEL = 0.004  # m: the top's picture resolution, finer than a phone sees it
MAX_TABLE_PICTURE = 1024  # px along the table's longer side
OBJECT_PICTURE = 256  # px: side of each object's texture atlas
BACKDROP_FACE = 64  # px: side of each face of the backdrop's cube map
OCCLUSION_MARGIN = 0.005  # m: a surface nearer the camera than this hides a point


@dataclass(frozen=True)
class FrameView:
    """A registered frame as a pinhole camera in the base frame (OpenCV axes)."""

    name: str
    image: np.ndarray  # (H, W, 3) RGB, undistorted
    intrinsics: np.ndarray  # (3, 3) of the undistorted image
    world_to_camera: np.ndarray  # (4, 4) base frame to camera

    @property
    def centre(self) -> np.ndarray:
        rotation, translation = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return -rotation.T @ translation

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel columns, rows (int) of base-frame ``points`` and whether each is in view."""
        camera = points @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]
        ahead = camera[:, 2] > 1e-3
        pixels = camera @ self.intrinsics.T
        pixels = pixels[:, :2] / np.where(ahead, camera[:, 2], 1.0)[:, None]
        pixels = np.clip(np.nan_to_num(pixels, nan=-1.0), -1.0, 1e6)
        u, v = np.floor(pixels).astype(int).T
        height, width = self.image.shape[:2]
        return u, v, ahead & (u >= 0) & (v >= 0) & (u < width) & (v < height)


def frame_views(model: SparseModel, image_dir: Path, to_cell: Similarity) -> list[FrameView]:
    """The walk's registered frames, by name, each undistorted to a centred pinhole at
    most :data:`MAX_WIDTH` wide."""
    undistortions: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    views = []
    for image in model.walk_images():
        if image.camera_id not in undistortions:  # the walk's frames share one camera
            undistortions[image.camera_id] = _undistortion(
                model.reconstruction.cameras[image.camera_id]
            )
        intrinsics, map_x, map_y = undistortions[image.camera_id]
        frame = cv2.imread(str(image_dir / image.name))[:, :, ::-1]
        undistorted = cv2.remap(
            frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        rotation = image.cam_from_world().rotation.matrix() @ to_cell.rotation.T
        centre = to_cell.apply(image.projection_center()[None])[0]
        world_to_camera = np.eye(4)
        world_to_camera[:3, :3], world_to_camera[:3, 3] = rotation, -rotation @ centre
        views.append(FrameView(image.name, undistorted, intrinsics, world_to_camera))
    return views


def _undistortion(camera: pycolmap.Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The centred pinhole (3, 3) a frame of ``camera`` is undistorted into, at most
    :data:`MAX_WIDTH` wide, and the source pixel maps (x, y) ``cv2.remap`` takes."""
    scale = min(1.0, MAX_WIDTH / camera.width)
    width, height = round(camera.width * scale), round(camera.height * scale)
    focal = camera.mean_focal_length() * scale
    intrinsics = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    columns, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.c_[
        (columns.ravel() - width / 2) / focal,
        (rows.ravel() - height / 2) / focal,
        np.ones(columns.size),
    ]
    source = np.nan_to_num(camera.img_from_cam(rays).reshape(height, width, 2) - 0.5, nan=-1)
    return intrinsics, source[..., 0].astype(np.float32), source[..., 1].astype(np.float32)


def split_views(views: list[FrameView]) -> tuple[list[FrameView], list[FrameView]]:
    """(painters, judges): every :data:`HELD_OUT_EVERY`-th frame judges, the rest
    (thinned to :data:`MAX_PAINTERS`, evenly) paint."""
    judging = HELD_OUT_EVERY // 2
    judges = views[judging::HELD_OUT_EVERY]
    rest = [v for k, v in enumerate(views) if k % HELD_OUT_EVERY != judging]
    keep = np.unique(np.linspace(0, len(rest) - 1, min(MAX_PAINTERS, len(rest))).round())
    return [rest[int(k)] for k in keep], judges


@dataclass(frozen=True)
class Lighting:
    """How the twin's lights render a surface of colour c (0-1): ``gain * c + offset``
    (the diffuse light scales a colour, the specular light adds to it)."""

    gain: float
    offset: float

    def colour_for(self, seen: np.ndarray) -> np.ndarray:
        """The colour (0-1) that the twin renders as ``seen`` (0-1)."""
        return np.clip((np.asarray(seen) - self.offset) / self.gain, 0.0, 1.0)


@dataclass
class CellLook:
    """The pictures a twin is dressed in."""

    table: np.ndarray  # (H, W, 3) the top: columns along its x, first row its +y edge
    backdrop: np.ndarray  # (6*S, S, 3) cube map of the base frame
    surfaces: dict[str, o3d.geometry.TriangleMesh]  # object frame, with UVs and picture
    table_seen: float  # share of the top's texels some frame saw
    painters: tuple[str, ...]
    judges: tuple[str, ...]

    def relight(self, lighting: dict[str, Lighting]) -> None:
        """Turn the table's and objects' pictures into the colours the twin's lights
        render as the frames show them (measured by ``look_score.twin_lighting``); the
        backdrop is unlit."""
        if "table" in lighting:
            self.table = _lit(self.table, lighting["table"])
        for name, surface in self.surfaces.items():
            if name in lighting:
                picture = np.asarray(surface.textures[0])
                surface.textures = [o3d.geometry.Image(_lit(picture, lighting[name]))]

    def write(self, out: Path) -> dict[str, Path]:
        """Write the pictures (the objects' surfaces as textured OBJs under
        ``out/meshes``); the paths, relative to ``out``, the scene spec names."""
        (out / "looks").mkdir(parents=True, exist_ok=True)
        (out / "meshes").mkdir(parents=True, exist_ok=True)
        paths = {"table": Path("looks/table.png"), "backdrop": Path("looks/backdrop.png")}
        Image.fromarray(self.table).save(out / paths["table"])
        Image.fromarray(self.backdrop).save(out / paths["backdrop"])
        for name, surface in self.surfaces.items():
            o3d.io.write_triangle_mesh(
                str(out / "meshes" / f"{name}.obj"), surface, write_triangle_uvs=True
            )
            paths[name] = Path(f"meshes/{name}_0.png")  # the OBJ writer names its picture
        return paths


def paint_cell(
    painters: list[FrameView],
    judges: list[FrameView],
    table: TablePlane,
    objects: list[TwinObject],
) -> CellLook:
    """Project the ``painters`` (:func:`split_views`) onto the table's top, each
    object's surface and the backdrop; the ``judges`` are only named."""
    occluders = o3d.t.geometry.RaycastingScene()
    for obj in objects:
        occluders.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(_placed(obj, table)))
    top, seen = _paint_table(painters, table, occluders)
    return CellLook(
        table=top,
        backdrop=_paint_backdrop(painters),
        surfaces={obj.name: _paint_surface(painters, obj, table, occluders) for obj in objects},
        table_seen=seen,
        painters=tuple(v.name for v in painters),
        judges=tuple(v.name for v in judges),
    )


def _placed(obj: TwinObject, table: TablePlane) -> o3d.geometry.TriangleMesh:
    """The object's surface where it stands, in the base frame."""
    return o3d.geometry.TriangleMesh(obj.shape.surface).transform(_placed_pose(obj, table))


def _median_colour(
    views: list[FrameView], points: np.ndarray, occluders: o3d.t.geometry.RaycastingScene
) -> np.ndarray:
    """Per base-frame point, the median colour of the frames that see it unhidden (NaN
    where none does)."""
    samples = np.full((len(views), len(points), 3), np.nan, np.float32)
    for k, view in enumerate(views):
        u, v, visible = view.project(points)
        if not visible.any():
            continue
        rays = points[visible] - view.centre
        distance = np.linalg.norm(rays, axis=1)
        query = np.c_[np.broadcast_to(view.centre, rays.shape), rays / distance[:, None]]
        hit = occluders.cast_rays(o3d.core.Tensor(query.astype(np.float32)))["t_hit"].numpy()
        clear = np.flatnonzero(visible)[hit > distance - OCCLUSION_MARGIN]
        samples[k, clear] = view.image[v[clear], u[clear]]
    return _nanmedian(samples)


def _paint_table(
    views: list[FrameView], table: TablePlane, occluders: o3d.t.geometry.RaycastingScene
) -> tuple[np.ndarray, float]:
    """The top's picture (columns along its x, first row at +y) and the share seen;
    texels no frame saw take the table's colour."""
    length, width = table.size
    texel = max(TABLE_TEXEL, max(length, width) / MAX_TABLE_PICTURE)
    columns, rows = max(2, round(length / texel)), max(2, round(width / texel))
    x = (np.arange(columns) + 0.5) / columns * length - length / 2
    y = width / 2 - (np.arange(rows) + 0.5) / rows * width
    local_x, local_y = np.meshgrid(x, y)
    cos, sin = np.cos(table.yaw), np.sin(table.yaw)
    points = np.c_[
        table.center[0] + cos * local_x.ravel() - sin * local_y.ravel(),
        table.center[1] + sin * local_x.ravel() + cos * local_y.ravel(),
        np.full(local_x.size, table.height),
    ]
    colour = _median_colour(views, points, occluders)
    unseen = np.isnan(colour).any(axis=1)
    colour[unseen] = 255 * np.asarray(table.color)
    picture = colour.reshape(rows, columns, 3).round().astype(np.uint8)
    return picture, float(1 - unseen.mean())


def _paint_backdrop(views: list[FrameView]) -> np.ndarray:
    """The room at infinity: per cube-map direction, the median colour of the frames
    looking that way (parallax blurs what is near); unseen directions take the mean."""
    directions = cube_directions(BACKDROP_FACE).reshape(-1, 3)
    samples = np.full((len(views), len(directions), 3), np.nan, np.float32)
    for k, view in enumerate(views):
        u, v, visible = view.project(view.centre + 1e3 * directions)  # a km: at infinity
        samples[k, visible] = view.image[v[visible], u[visible]]
    colour = _nanmedian(samples)
    unseen = np.isnan(colour).any(axis=1)
    colour[unseen] = np.nanmean(colour[~unseen], axis=0) if (~unseen).any() else 128
    return colour.reshape(6 * BACKDROP_FACE, BACKDROP_FACE, 3).round().astype(np.uint8)


def _paint_surface(
    views: list[FrameView],
    obj: TwinObject,
    table: TablePlane,
    occluders: o3d.t.geometry.RaycastingScene,
) -> o3d.geometry.TriangleMesh:
    """The object's surface (its own frame) with a texture atlas: per texel, the
    median colour of the frames that see its point on the surface unhidden, by the
    object itself or another; texels none sees take its colour."""
    painted = _atlas(obj.shape.surface)
    placed = o3d.geometry.TriangleMesh(painted).transform(_placed_pose(obj, table))
    corners = np.asarray(placed.vertices)[np.asarray(painted.triangles)]
    uvs = np.asarray(painted.triangle_uvs).reshape(-1, 3, 2)
    # Which triangle each texel lies in (texel row r at v = (r + 0.5) / size, as an OBJ
    # texture coordinate reads in MuJoCo), then its point by barycentric coordinates.
    size = OBJECT_PICTURE
    owner = np.full((size, size), -1, np.int32)
    for index, triangle in enumerate(uvs):
        cv2.fillPoly(owner, [np.round(triangle * size * 16).astype(np.int32)], index, shift=4)
    rows, columns = np.nonzero(owner >= 0)
    triangles = owner[rows, columns]
    texel = np.c_[columns + 0.5, rows + 0.5] / size
    a, b, c = uvs[triangles, 0], uvs[triangles, 1], uvs[triangles, 2]
    edges = np.stack([b - a, c - a], axis=2)  # (N, 2, 2): uv = a + edges @ (w1, w2)
    weights = np.linalg.solve(edges + 1e-12 * np.eye(2), (texel - a)[..., None])[..., 0]
    weights = np.clip(weights, 0.0, 1.0)
    points = (
        corners[triangles, 0]
        + weights[:, :1] * (corners[triangles, 1] - corners[triangles, 0])
        + weights[:, 1:] * (corners[triangles, 2] - corners[triangles, 0])
    )
    colour = _median_colour(views, points, occluders)
    picture = np.empty((size, size, 3), np.float32)
    picture[:] = 255 * np.asarray(obj.color)
    seen = ~np.isnan(colour).any(axis=1)
    picture[rows[seen], columns[seen]] = colour[seen]
    painted.triangle_normals = o3d.utility.Vector3dVector()  # OBJ keeps vertex normals only
    painted.textures = [o3d.geometry.Image(picture.round().astype(np.uint8))]
    painted.triangle_material_ids = o3d.utility.IntVector([0] * len(painted.triangles))
    return painted


def _atlas(surface: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    """``surface`` cut into charts laid out on an :data:`OBJECT_PICTURE` square
    (xatlas), its vertices split along the seams: the same surface always gets the
    same layout (open3d's UVAtlas draws from an unseeded random device, so two builds
    of one seed dressed their objects differently)."""
    atlas = xatlas.Atlas()
    atlas.add_mesh(
        np.asarray(surface.vertices, np.float32), np.asarray(surface.triangles, np.uint32)
    )
    packing = xatlas.PackOptions()
    packing.resolution, packing.padding = OBJECT_PICTURE, 1
    atlas.generate(pack_options=packing)
    kept, triangles, uvs = atlas[0]
    painted = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(surface.vertices)[kept]),
        o3d.utility.Vector3iVector(triangles.astype(np.int32)),
    )
    if surface.has_vertex_normals():
        painted.vertex_normals = o3d.utility.Vector3dVector(
            np.asarray(surface.vertex_normals)[kept]
        )
    painted.triangle_uvs = o3d.utility.Vector2dVector(uvs[triangles].reshape(-1, 2))
    return painted


def _placed_pose(obj: TwinObject, table: TablePlane) -> np.ndarray:
    """The object's frame in the base frame (4, 4)."""
    pose = np.eye(4)
    pose[:3, :3] = o3d.geometry.get_rotation_matrix_from_axis_angle([0.0, 0.0, obj.yaw])
    pose[:3, 3] = [*obj.position, table.height + obj.shape.half_height]
    return pose


def _lit(picture: np.ndarray, lighting: Lighting) -> np.ndarray:
    return (255 * lighting.colour_for(picture / 255)).round().astype(np.uint8)


def _nanmedian(samples: np.ndarray) -> np.ndarray:
    """Median over the first axis, NaN where all are NaN (points no frame saw)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(samples, axis=0)
