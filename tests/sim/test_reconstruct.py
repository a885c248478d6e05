"""``twinrl twin build`` on a rendered walk-around clip: frames, SfM, alignment to the
base (one tag's pose, or three tags' centres), table, objects, the front camera from a
photo and the scene spec, against the scene that rendered them; and the clips and
arguments it must refuse."""

import dataclasses
import tempfile
from pathlib import Path

import cv2
import mujoco
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from tests.test_cli import twinrl
from twinrl_robot.scripted import run_scripted_expert
from twinrl_sim.build import compile_scene, look_at_quat
from twinrl_sim.reconstruct import CaptureError, align_to_points, align_to_tag, select_frames
from twinrl_sim.reconstruct.look import _atlas
from twinrl_sim.reconstruct.objects import match_task_objects, reconstruct_shape, template_sizes
from twinrl_sim.reconstruct.pipeline import BuildSettings, _inside, build_twin
from twinrl_sim.reconstruct.segment import (
    TablePlane,
    TagPlane,
    describe_cluster,
    find_objects,
    level_table,
)
from twinrl_sim.reconstruct.synthetic import (
    THREE_TAGS,
    TagPlacement,
    WalkthroughSettings,
    render_fixed_view,
    render_walkthrough,
)
from twinrl_sim.reconstruct.table_extent import TableColour, read_colour
from twinrl_sim.reconstruct.tag import (
    DEFAULT_FAMILY,
    FAMILIES,
    detect,
    family,
    other_families_seen,
    tag_image,
)
from twinrl_sim.spec import load_spec
from twinrl_sim.tasks import make_task

SCENE = make_task("pick_place").scene
CLIP = WalkthroughSettings(seconds=6.0, fps=10.0)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    root = tmp_path_factory.mktemp("walk")
    walk = render_walkthrough(SCENE, root / "walk.mp4", tags=THREE_TAGS, settings=CLIP, seed=0)
    front = render_fixed_view(SCENE, "front", root / "front.png", tags=THREE_TAGS)
    return walk, front


def _tag_pose_args(walk, size: float | None = None) -> list[str]:
    pose = " ".join(map(str, walk.tag_poses[0]))
    return ["--tag-size", str(size or walk.tags[0].size), "--tag-pose", pose, "--tag-id", "0"]


def _centres(walk) -> dict[int, tuple[float, ...]]:
    return {tag_id: tuple(pose[:3]) for tag_id, pose in walk.tag_poses.items()}


@pytest.fixture(scope="module")
def built(clip, tmp_path_factory):
    walk, front = clip
    settings = BuildSettings(
        tag_size=walk.tags[0].size,
        tag_pose=tuple(walk.tag_poses[0]),
        tag_id=0,
        task="pick_place",
        camera_images={"front": front},
        frames=40,
        keep_work=True,
    )
    return build_twin(walk.video, tmp_path_factory.mktemp("built") / "cell", settings)


def test_frames_are_sharp_and_spread_over_the_walk(built):
    frames, model = built.selection, built.model
    assert len(frames.paths) == 40 and frames.frames_in_clip == 60
    assert np.all(np.diff(frames.source_indices) > 0) and frames.travel > 0.25
    assert model.registered == 40  # every kept frame is in the reconstruction


def test_the_tag_gives_metric_scale_and_the_base_frame(built, clip):
    walk, _ = clip
    assert built.alignment.residual_m < 0.002 and built.alignment.views >= 20
    # Every recovered camera is where the renderer put it (to about 1 % of its 1 m
    # distance: the scale comes from an 8 cm tag).
    truth = walk.camera_positions[built.selection.source_indices]
    errors = np.linalg.norm(built.camera_path - truth, axis=1)
    assert np.median(errors) < 0.02 and len(errors) == built.model.registered
    table = built.table
    assert abs(table.height - SCENE.table.top_height) < 0.005 and table.tilt_deg < 2.0
    assert abs(np.degrees(table.yaw)) < 2.0
    # Size, place and colour come from the frames (every edge was in view), not from the
    # table's few SfM points, whose patch changes from run to run.
    assert table.extent_from == "frames" and set(table.sides_seen) == {"-x", "+x", "-y", "+y"}
    assert np.all(np.abs(table.size - SCENE.table.size) < 0.03)
    assert np.linalg.norm(table.center - SCENE.table.center) < 0.02
    assert np.all(np.abs(table.color - np.array(SCENE.table.rgba[:3])) < 0.06)


def test_objects_are_found_named_and_measured(built):
    objects = {o.name: o for o in built.objects}
    assert set(objects) == {"banana", "plate"}  # named after the task's objects
    assert objects["banana"].role == "manipulated" and objects["plate"].role == "target"
    plate, banana = objects["plate"], objects["banana"]
    truth = template_sizes(SCENE)  # footprint centre; long, short, height
    for obj, size_tolerance in ((plate, 0.1), (banana, 0.1)):
        centre, extent = truth[obj.name]
        size = np.array([*sorted(obj.cluster.size[:2], reverse=True), obj.cluster.size[2]])
        print(obj.name, obj.position - centre, size / extent - 1)
        assert np.linalg.norm(obj.position - centre) < 0.01
        assert np.all(np.abs(size / extent - 1) < size_tolerance)
    # The yellow banana's footprint is carved from its silhouettes (its ends have few
    # points); the white plate does not stand out from the table's colour: points only.
    assert banana.cluster.carved is not None and plate.cluster.carved is None
    assert banana.source == "points + silhouettes" and plate.source == "points"
    assert abs(np.degrees(banana.yaw)) < 5.0
    assert plate.yaw == 0.0  # round: no heading
    assert banana.color[0] > 0.5 and banana.color[2] < 0.3  # yellow
    # Closed surfaces, split into convex parts; the banana weighs what its volume says.
    banana_volume = sum(np.pi * 0.017**2 * 2 * 0.0412 + 4 / 3 * np.pi * 0.017**3 for _ in range(2))
    assert abs(banana.shape.volume - banana_volume) < 0.3 * banana_volume
    assert banana.mass == pytest.approx(700 * banana.shape.volume)
    assert 1 <= len(banana.shape.parts) <= 8 and banana.shape.surface.is_watertight()


def _disc_points(rng, radius, n, *, stretch=1.0, covered=np.pi):
    """Points over a disc (or an ellipse ``stretch`` times longer in x) 2 cm high, the
    rim covered only in the angles within ``covered`` of +x, as a short clip sees it."""
    angle = rng.uniform(-np.pi, np.pi, n)
    reach = np.where(np.abs(angle) < covered, 1.0, 0.7) * np.sqrt(rng.uniform(0, 1, n))
    xy = radius * reach[:, None] * np.c_[stretch * np.cos(angle), np.sin(angle)]
    return np.c_[xy, rng.uniform(0.01, 0.02, n)]


def test_a_round_footprint_has_one_diameter_however_unevenly_its_rim_is_seen():
    rng = np.random.default_rng(0)
    table = TablePlane(0.0, np.zeros(2), np.ones(2), 0.0, np.ones(3), 0.0, 100)
    # Half the rim seen: across that side the trimmed box spans about 0.79 of the 17 cm
    # diameter, along it 0.87 (full coverage: 0.93, the trim of a uniform disc).
    plate = describe_cluster(_disc_points(rng, 0.085, 400, covered=np.pi / 2), np.ones(3), table)
    assert plate.size[0] == plate.size[1] and 0.85 < plate.size[0] / 0.17 < 1.0
    # An elongated footprint keeps its two extents.
    bar = describe_cluster(_disc_points(rng, 0.03, 400, stretch=3.0), np.ones(3), table)
    assert 0.85 < bar.size[0] / 0.18 < 1.0 and 0.85 < bar.size[1] / 0.06 < 1.0


def _streak(rng, xy, height, n=80):
    """Points up a thin vertical line from the table at ``xy``: the outline of a clear
    object where it bends the background, as structure from motion finds it."""
    return np.c_[np.asarray(xy) + rng.normal(0, 0.002, (n, 2)), rng.uniform(0.01, height, n)]


def _box(rng, xy, side, n=200):
    return np.c_[
        np.asarray(xy) + rng.uniform(-side / 2, side / 2, (n, 2)), rng.uniform(0.01, side, n)
    ]


def test_a_clear_objects_outline_streaks_become_one_object_as_wide_as_it_looks():
    rng = np.random.default_rng(1)
    table = TablePlane(0.0, np.zeros(2), np.ones(2), 0.0, np.ones(3), 0.0, 100)
    # A bottle 7.5 cm across, 25 cm tall: its two sides as seen from +x; 40 cm away two
    # cubes 5 cm apart, a pen 14 cm tall and a second bottle.
    clouds = [
        _streak(rng, (0.0, -0.0375), 0.25),
        _streak(rng, (0.003, 0.0375), 0.25),
        _box(rng, (0.4, 0.0), 0.04),
        _box(rng, (0.4, 0.09), 0.04),
        _streak(rng, (0.0, 0.2), 0.14),
        _streak(rng, (-0.2, -0.2), 0.25),
        _streak(rng, (-0.2, -0.27), 0.25),
    ]
    points = np.vstack(clouds)
    objects = find_objects(points, np.full((len(points), 3), 128.0), table)
    assert len(objects) == 5  # the two bottles, the two cubes, the pen
    bottles = sorted((o for o in objects if o.outline), key=lambda o: -o.center[0])
    assert [o.outline for o in bottles] == [2, 2]
    assert np.linalg.norm(bottles[0].center[:2] - [0.0015, 0.0]) < 0.005
    assert bottles[0].size[0] == bottles[0].size[1] == pytest.approx(0.075, abs=0.01)
    assert abs(bottles[0].size[2] - 0.25) < 0.02
    assert sum(o.outline == 0 for o in objects) == 3
    # Its unseen back: a closed surface as deep as it is wide, a cylinder's volume.
    shape = reconstruct_shape(bottles[0], bottles[0].yaw, table.height)
    extent = np.ptp(np.asarray(shape.surface.vertices), axis=0)
    assert shape.surface.is_watertight() and extent[1] == pytest.approx(extent[0], rel=0.05)
    radius, height = bottles[0].size[0] / 2, bottles[0].size[2]
    assert shape.volume == pytest.approx(np.pi * radius**2 * height, rel=0.1)


def _pixels(rgb, n: int, rng, brightness=(1.0, 1.0), noise: float = 3.0) -> np.ndarray:
    """``n`` pixels of colour ``rgb`` (0-255) lit between ``brightness``, with sensor noise,
    as :func:`read_colour` values."""
    lit = np.asarray(rgb, float) * rng.uniform(*brightness, (n, 1)) + rng.normal(0, noise, (n, 3))
    image = np.clip(lit, 0, 255).astype(np.uint8).reshape(1, n, 3)[:, :, ::-1]
    path = Path(tempfile.mkdtemp()) / "pixels.png"
    cv2.imwrite(str(path), image)
    return read_colour(path).reshape(n, 3)


@pytest.mark.parametrize(
    ("table", "brightness", "floor"),
    [
        ((235, 235, 230), (0.95, 1.0), (150, 150, 150)),  # a plain white top, a grey floor
        ((140, 115, 90), (0.35, 1.0), (77, 77, 82)),  # wood with dark patches, a dark floor
    ],
)
def test_the_tables_colour_is_told_from_the_floor_despite_objects_in_view(table, brightness, floor):
    rng = np.random.default_rng(0)
    top = _pixels(table, 3000, rng, brightness)
    # The core of the top also shows a white plate, a yellow banana and a tag's black.
    clutter = [_pixels(c, 300, rng) for c in ((250, 250, 250), (220, 200, 40), (20, 20, 20))]
    colour = TableColour.fit(np.concatenate([top, *clutter]))
    assert colour.alike(_pixels(table, 1000, rng, brightness)).mean() > 0.95
    assert colour.alike(_pixels(floor, 1000, rng, (0.9, 1.1))).mean() < 0.02
    assert colour.alike(clutter[1]).mean() < 0.02


def _table_and_wall(rng, tilt_deg: float = 0.0) -> np.ndarray:
    """A sparse table top (400 points, tilted ``tilt_deg`` about x) and a textured wall
    behind it with four times as many: what a plain office table in front of a poster
    gives structure from motion."""
    xy = rng.uniform([0.0, -0.5], [0.9, 0.5], (400, 2))
    top = np.c_[xy, np.tan(np.radians(tilt_deg)) * xy[:, 1]]
    wall = np.c_[np.full(1600, 1.3), rng.uniform(-1, 1, 1600), rng.uniform(0.0, 1.2, 1600)]
    return np.vstack([top, wall]) + rng.normal(0, 0.001, (2000, 3))


def test_the_table_is_sought_where_the_tags_lie_not_on_the_largest_plane():
    rng = np.random.default_rng(0)
    points = _table_and_wall(rng)
    colors = np.full((len(points), 3), 128, np.uint8)
    tags = TagPlane(np.array([0.5, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    # The largest plane is the wall: 90 degrees from where the tags lie.
    table, _, _ = level_table(points, colors, np.zeros(3))
    assert table.tilt_deg > 80
    table, _, _ = level_table(points, colors, np.zeros(3), tags=tags)
    assert table.tilt_deg < 0.5 and abs(table.height) < 0.002 and table.inliers >= 380
    # A top tilted 6 degrees from the tags lying on it is refused, not levelled.
    with pytest.raises(CaptureError, match="tilted .* from the tags' plane.*`tags_on_table` off"):
        level_table(_table_and_wall(rng, 6.0), colors, np.zeros(3), tags=tags)
    # No points near the tags' plane (only the wall, above the table): say so.
    wall = points[400:][points[400:, 2] > 0.05]
    with pytest.raises(CaptureError, match="within 3 cm of the tags' plane"):
        level_table(wall, colors[: len(wall)], np.zeros(3), tags=tags)


def test_the_front_camera_is_placed_from_its_photo(built):
    truth = SCENE.cameras[0]
    placed = built.scene.cameras[0]
    assert placed.name == "front" and placed.mount == "world"
    assert np.linalg.norm(np.subtract(placed.pos, truth.pos)) < 0.03
    assert abs(placed.fovy - truth.fovy) < 2.0
    true_quat = look_at_quat(np.array(truth.pos), np.array(truth.lookat), np.array([0, 0, 1.0]))
    placed_quat = look_at_quat(np.array(placed.pos), np.array(placed.lookat), np.array(placed.up))
    angle = 2 * np.arccos(min(1.0, abs(np.dot(true_quat, placed_quat))))
    assert np.degrees(angle) < 2.0


def test_the_built_scene_is_a_twin_the_expert_succeeds_in(built):
    scene = load_spec(built.scene_path)  # from disk: the YAML and its mesh files
    assert scene.digest == built.scene.digest
    compiled = compile_scene(scene)
    banana = compiled.model.body("banana")
    assert banana.mass[0] == pytest.approx(scene.object("banana").mass, rel=1e-6)
    assert abs(scene.table.top_height) < 0.005
    report = run_scripted_expert("pick_place", episodes=2, scene=scene)
    assert all(e.success for e in report.episodes), report.episodes
    text = (built.scene_path.parent / "report.md").read_text()
    assert "| banana | manipulated |" in text and "## Cameras placed from photos" in text
    for name in ("cloud.png", "alignment.png", "reconstruction.rrd", "meshes/banana.obj"):
        assert (built.scene_path.parent / name).stat().st_size > 1000


@pytest.mark.long  # ~30 s, beyond CI's time (make test-long)
def test_a_supplied_mesh_is_registered_to_its_points_by_icp(clip, tmp_path):
    walk, _ = clip
    mesh_file = tmp_path / "banana.stl"
    o3d.io.write_triangle_mesh(str(mesh_file), _banana_mesh())
    # The base frame from three tags' centres this time (no tag size needed).
    centres = [f"--tag-point={i}={','.join(map(str, xyz))}" for i, xyz in _centres(walk).items()]
    result = twinrl(
        "twin", "build", str(walk.video), "--out", str(tmp_path / "cell"), *centres,
        "--task", "pick_place", "--object-mesh", f"banana={mesh_file}", "--frames", "40",
        "--no-look",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "banana" in result.stdout and "scene.yaml" in result.stdout
    scene = load_spec(tmp_path / "cell" / "scene.yaml")
    banana = scene.object("banana")
    centre, extent = template_sizes(SCENE)["banana"]
    assert np.linalg.norm(np.subtract(banana.pos[:2], centre)) < 0.01
    assert abs(np.degrees(np.angle(np.exp(1j * banana.yaw)))) < 5.0  # bent: no symmetry
    assert banana.pos[2] == pytest.approx(extent[2] / 2, abs=1e-3)  # the mesh's own size
    assert not (tmp_path / "cell" / "work").exists()  # intermediate files are removed
    report = (tmp_path / "cell" / "report.md").read_text()
    assert (
        "banana.stl (ICP" in report and "| alignment | tag centres (tag 0, tag 1, tag 2)" in report
    )
    assert abs(scene.table.top_height) < 0.005
    # Without the look: flat colours, no pictures written, none judged.
    assert scene.table.image is None and scene.backdrop is None and banana.look is None
    assert "The cell's look" not in report and not (tmp_path / "cell" / "looks").exists()


def test_the_twin_wears_the_frames_look_and_resembles_frames_it_was_not_painted_from(built):
    look, score = built.look, built.look_score
    assert look is not None and score is not None
    assert score.frames >= 5 and not set(look.judges) & set(look.painters)
    assert look.table_seen > 0.5
    # The textured table and objects, against their flat colours, from held-out poses.
    assert score.psnr > score.flat_psnr + 2.0 and score.ssim > score.flat_ssim + 0.02
    scene = built.scene
    assert scene.table.image is not None and scene.backdrop is not None
    assert all(obj.look is not None for obj in scene.objects)
    folder = built.scene_path.parent
    assert (folder / "look.png").is_file() and "## The cell's look" in (
        folder / "report.md"
    ).read_text()


def test_an_objects_picture_is_laid_out_alike_in_every_build():
    """Two builds of one seed dressed an object differently (UVAtlas draws from an
    unseeded random device); the atlas now gives one surface one layout, each corner
    a point of the surface and inside the picture."""
    surface = o3d.geometry.TriangleMesh.create_cylinder(0.035, 0.23, 24, 6)
    first, second = _atlas(surface), _atlas(surface)
    uvs = np.asarray(first.triangle_uvs)
    np.testing.assert_array_equal(uvs, np.asarray(second.triangle_uvs))
    np.testing.assert_array_equal(np.asarray(first.triangles), np.asarray(second.triangles))
    assert len(first.triangles) == len(surface.triangles) and len(uvs) == 3 * len(first.triangles)
    assert uvs.min() >= 0.0 and uvs.max() <= 1.0
    on_surface = cKDTree(np.asarray(surface.vertices)).query(np.asarray(first.vertices))[0]
    assert on_surface.max() < 1e-9


def test_a_wrong_tag_size_is_named_and_nothing_is_left(clip, built, tmp_path):
    walk, _ = clip
    # Centimetres given as metres' tenths: the phone would have been 10 m away.
    result = twinrl(
        "twin", "build", str(walk.video), "--out", str(tmp_path / "cell"),
        *_tag_pose_args(walk, size=0.8), "--frames", "40",
    )  # fmt: skip
    assert result.returncode == 2
    assert "the phone was 10." in result.stderr and "--tag-size must be the edge" in result.stderr
    assert not (tmp_path / "cell").exists()
    # A subtler error shows in the objects: the white margin measured too (twice the edge).
    clusters = [dataclasses.replace(o.cluster, size=2.0 * o.cluster.size) for o in built.objects]
    with pytest.raises(CaptureError, match=r"come out 1\.[6-9]\dx.*without the white margin"):
        match_task_objects(clusters, SCENE)
    names, ratio = match_task_objects([o.cluster for o in built.objects], SCENE)
    assert sorted(names.values()) == ["banana", "plate"] and 0.85 < ratio < 1.1


TAG = ["--tag-size", "0.08", "--tag-pose", "0.3 0.3 0 1 0 0 0"]
POINTS = ["--tag-point", "0=0.3,0.3,0", "--tag-point", "1=0.7,0.4,0"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--tag-size", "8", *TAG[2:]], "not a tag edge in metres"),
        ([*TAG[:2], "--tag-pose", "0.3 0.3 0"], "needs 7 numbers"),
        (TAG[2:], "--tag-pose needs --tag-size"),
        ([], "give --tag-size and --tag-pose of one tag, or --tag-point"),
        ([*TAG, *POINTS, "--tag-point", "2=0.2,-0.4,0"], "not both"),
        (POINTS, "for 2 tag(s); give the centres of 3 or more"),
        ([*POINTS, "--tag-point", "2=1.1,0.5,0"], "lie (almost) on a line"),
        ([*POINTS, "--tag-point", "2=0.2,-0.4"], "--tag-point 2 needs 3 numbers"),
        ([*POINTS, "--tag-point", "two=0.2,-0.4,0"], "must be a whole number"),
        ([*TAG, "--camera-image", "wrist=x.png"], "no such file"),
        ([*TAG, "--object-mesh", "apple=x.stl", "--task", "pick_place"], "no such file"),
        ([*TAG, "--density", "banana"], "must look like NAME=VALUE"),
        ([*TAG, "--task", "pick_plce"], "did you mean 'pick_place'"),
        ([*TAG, "--tag-family", "qr"], "--tag-family 'qr' is not one of tag36h11, tag36h10"),
        ([*TAG, "--intrinsics", "600 600 320"], "--intrinsics needs 4 numbers 'fx fy cx cy'"),
        ([*TAG, "--intrinsics", "600 -600 320 240"], "--intrinsics fx fy cx cy must be positive"),
        ([*TAG, "--refine-distortion"], "--refine-distortion refines the lens of known"),
        ([*TAG, "--workspace", "0 -1 -0.1 1 1"], "--workspace needs 6 numbers"),
        ([*TAG, "--matching", "vocab"], "--matching 'vocab' is not one of sequential"),
        ([*TAG, "--workspace", "1 -1 -0.1 0 1 0.5"], "each minimum must be below its maximum"),
    ],
)
def test_bad_arguments_are_refused_before_any_work(tmp_path, args, message):
    build = ["twin", "build", str(tmp_path), "--out", str(tmp_path / "o"), *args]
    result = twinrl(*build, cwd=tmp_path)
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_the_workspace_box_cuts_the_background_before_any_fitting():
    rng = np.random.default_rng(0)
    table = np.c_[rng.uniform(0.1, 0.9, 500), rng.uniform(-0.5, 0.5, 500), np.zeros(500)]
    wall = np.c_[np.full(300, 2.5), rng.uniform(-1, 1, 300), rng.uniform(0, 2, 300)]
    colours = np.r_[np.full((500, 3), 200), np.full((300, 3), 50)].astype(np.uint8)
    points, kept = _inside(np.r_[table, wall], colours, (0.0, -0.6, -0.1, 1.0, 0.6, 0.5))
    assert len(points) == 500 and np.all(kept == 200)
    with pytest.raises(CaptureError, match=r"only 0 of 800 points lie inside `workspace`"):
        _inside(np.r_[table, wall], colours, (3.0, 3.0, 3.0, 4.0, 4.0, 4.0))


def test_cameras_and_meshes_must_fit_the_task(tmp_path):
    photo = tmp_path / "wrist.png"
    photo.write_bytes(b"")
    args = ["--tag-size", "0.08", "--tag-pose", "0.3 0.3 0 1 0 0 0", "--task", "pick_place"]
    out = ["--out", str(tmp_path / "o")]
    wrist = twinrl("twin", "build", str(tmp_path), *out, *args, "--camera-image", f"wrist={photo}")
    assert wrist.returncode == 2 and "only fixed cameras" in wrist.stderr
    apple = twinrl("twin", "build", str(tmp_path), *out, *args, "--object-mesh", f"apple={photo}")
    assert apple.returncode == 2 and "has no object 'apple'" in apple.stderr
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "keep.txt").write_text("mine")
    busy = twinrl("twin", "build", str(tmp_path), *out, *args)
    assert busy.returncode == 2 and "not empty" in busy.stderr
    assert (tmp_path / "o" / "keep.txt").read_text() == "mine"


def _banana_mesh():
    """The banana of the built-in cell as a triangle mesh in its own frame (a user's CAD)."""
    banana = SCENE.object("banana")
    parts = o3d.geometry.TriangleMesh()
    for geom in banana.geoms:
        if not geom.contact:
            continue
        radius, half = geom.size
        capsule = o3d.geometry.TriangleMesh.create_cylinder(radius, 2 * half, 24, 4)
        for end in (-half, half):
            capsule += o3d.geometry.TriangleMesh.create_sphere(radius, 12).translate([0, 0, end])
        rotation = np.zeros(9)
        quat = np.zeros(4)
        mujoco.mju_euler2Quat(quat, np.array(geom.euler), "xyz")
        mujoco.mju_quat2Mat(rotation, quat)
        capsule.rotate(rotation.reshape(3, 3), center=[0, 0, 0]).translate(geom.pos)
        parts += capsule
    parts.compute_triangle_normals()  # STL stores one per face
    return parts


def test_a_static_clip_is_refused(tmp_path):
    still = WalkthroughSettings(seconds=3.0, static=True)
    walk = render_walkthrough(SCENE, tmp_path / "still.mp4", settings=still)
    with pytest.raises(CaptureError, match="the camera barely moves.*walk around the table"):
        select_frames(walk.video, tmp_path / "frames")
    assert not (tmp_path / "frames").exists()


def test_a_blurry_clip_is_refused(tmp_path, built):
    blurred = tmp_path / "blurred"
    blurred.mkdir()
    for path in built.selection.paths[:20]:
        cv2.imwrite(str(blurred / path.name), cv2.GaussianBlur(cv2.imread(str(path)), (0, 0), 6))
    with pytest.raises(CaptureError, match="only 0 of 20 frames are sharp.*film slower"):
        select_frames(blurred, tmp_path / "frames")


def test_three_tag_centres_tie_the_cell_to_the_base_like_one_tag_pose(built, clip):
    walk, _ = clip
    frames = built.selection.paths[0].parent
    alignment = align_to_points(built.model, frames, _centres(walk))
    assert alignment.labels == ("tag 0", "tag 1", "tag 2") and alignment.residual_m < 0.003
    assert alignment.to_base.scale == pytest.approx(built.alignment.to_base.scale, rel=0.01)
    # The recovered camera path, before levelling, lands where the renderer put it.
    walk_images = sorted(
        (
            image
            for image in built.model.reconstruction.images.values()
            if image.name not in built.model.fixed_images.values()
        ),
        key=lambda image: image.name,
    )
    path = alignment.to_base.apply(np.array([i.projection_center() for i in walk_images]))
    truth = walk.camera_positions[built.selection.source_indices]
    assert np.median(np.linalg.norm(path - truth, axis=1)) < 0.02
    # The outlines of the tags come out at their true size (6-8 cm), though none was given.
    edges = [np.linalg.norm(o[1] - o[0]) for o in alignment.tag_outlines]
    assert edges == pytest.approx([t.size for t in THREE_TAGS], rel=0.05)


def test_tag_centres_that_do_not_fit_are_named(built, clip):
    walk, _ = clip
    frames = built.selection.paths[0].parent
    moved = _centres(walk) | {2: (0.25, -0.35, 0.0)}  # 10 cm off: a mis-typed coordinate
    with pytest.raises(CaptureError, match="do not fit one rigid frame.*re-measure the centres"):
        align_to_points(built.model, frames, moved)
    missing = _centres(walk) | {5: (0.6, -0.1, 0.0)}
    with pytest.raises(CaptureError, match="id 5 was found in fewer than 3.*tags seen: 0, 1, 2"):
        align_to_points(built.model, frames, missing)
    with pytest.raises(CaptureError, match=r"several tags are in view \(0, 1, 2\).*`tag_id`"):
        align_to_tag(built.model, frames, walk.tag_poses[0], 0.08)


def test_a_missing_tag_or_another_family_is_named(built, clip):
    walk, _ = clip
    frames = built.selection.paths[0].parent
    with pytest.raises(CaptureError, match="AprilTag 36h11 id 7 was found in fewer than 3"):
        align_to_tag(built.model, frames, walk.tag_poses[0], 0.08, tag_id=7)
    marker = cv2.aruco.generateImageMarker(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_250), 3, 200
    )
    assert other_families_seen(np.pad(marker, 40, constant_values=255)) == ["aruco4x4"]


@pytest.mark.parametrize("name", list(FAMILIES))
def test_every_family_prints_and_reads_back_with_its_corners(name):
    cell_px, pad = 12, 40
    image = np.pad(tag_image(5, cell_px, 1, name), pad, constant_values=255)
    (found,) = [d for d in detect(image, family_name=name) if d.tag_id == 5]
    low = pad + cell_px - 0.5  # the black square starts after the white margin cell
    high = low + family(name).cells * cell_px
    square = np.array([[low, low], [high, low], [high, high], [low, high]])
    assert np.abs(found.corners - square).max() < 1.0
    # Read with the default family, a tag of another one is not taken for a 36h11 tag 5.
    if name != DEFAULT_FAMILY:
        assert not [d for d in detect(image) if d.tag_id == 5]


@pytest.mark.slow
def test_a_build_reads_the_tag_family_it_is_told(tmp_path):
    tag = TagPlacement(family="aruco5x5", size=0.1)
    walk = render_walkthrough(SCENE, tmp_path / "walk.mp4", tags=(tag,), settings=CLIP, seed=1)
    settings = BuildSettings(
        tag_size=tag.size,
        tag_pose=tuple(walk.tag_poses[0]),
        tag_family="aruco5x5",
        frames=30,
        keep_work=True,
    )
    built = build_twin(walk.video, tmp_path / "cell", settings)
    assert built.alignment.residual_m < 0.002
    truth = walk.camera_positions[built.selection.source_indices]
    assert np.median(np.linalg.norm(built.camera_path - truth, axis=1)) < 0.02
    frames = built.selection.paths[0].parent
    with pytest.raises(
        CaptureError, match="ArUco 5x5 markers instead: set `tag_family` to aruco5x5"
    ):
        align_to_tag(built.model, frames, walk.tag_poses[0], tag.size)


@pytest.mark.slow
def test_known_intrinsics_are_held_fixed_and_recorded(clip, tmp_path):
    walk, _ = clip
    focal = (CLIP.height / 2) / np.tan(np.radians(walk.fovy_deg) / 2)
    known = (focal, focal, CLIP.width / 2, CLIP.height / 2)
    settings = BuildSettings(
        tag_size=walk.tags[0].size,
        tag_pose=tuple(walk.tag_poses[0]),
        tag_id=0,
        intrinsics=known,
        frames=30,
        keep_work=True,
    )
    built = build_twin(walk.video, tmp_path / "cell", settings)
    (camera,) = built.model.reconstruction.cameras.values()
    assert camera.model.name == "PINHOLE" and np.allclose(camera.params, known)
    assert built.model.registered == 30 and built.alignment.residual_m < 0.002
    truth = walk.camera_positions[built.selection.source_indices]
    assert np.median(np.linalg.norm(built.camera_path - truth, axis=1)) < 0.02
    scene = load_spec(built.scene_path)
    assert scene.provenance["intrinsics"] == pytest.approx(list(known))


def test_the_tag_family_setting_lists_every_family():
    from twinrl_sim.reconstruct import settings

    assert BuildSettings().tag_family == DEFAULT_FAMILY
    source = Path(settings.__file__).read_text()
    described = source.split("tag_family: str")[1].split("tags_on_table")[0]
    words = set(described.replace(",", " ").replace("(", " ").replace(")", " ").split())
    assert set(FAMILIES) <= words


def test_unreadable_sources_say_what_to_give(tmp_path):
    with pytest.raises(CaptureError, match="does not exist"):
        select_frames(tmp_path / "nope.mp4", tmp_path / "f")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CaptureError, match="holds no images"):
        select_frames(tmp_path / "empty", tmp_path / "f")
    (tmp_path / "bad.mp4").write_text("not a video")
    with pytest.raises(CaptureError, match="not a readable video"):
        select_frames(tmp_path / "bad.mp4", tmp_path / "f")
