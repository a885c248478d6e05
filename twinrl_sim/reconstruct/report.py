"""What ``twinrl twin build`` shows: plots, a Markdown report and a Rerun recording of
the point cloud, the camera path and the MuJoCo scene that came out."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np
import rerun as rr
from PIL import Image

from twinrl_data.atomic import write_text_atomic
from twinrl_sim.build import CompiledScene
from twinrl_sim.gap.report import _pyplot
from twinrl_sim.reconstruct.segment import TablePlane, planar_axes
from twinrl_sim.reconstruct.table_extent import SIDES

if TYPE_CHECKING:
    from twinrl_sim.reconstruct.candidates import DroppedCandidate
    from twinrl_sim.reconstruct.result import TwinBuild
    from twinrl_sim.reconstruct.sfm import SparseModel


def _rectangle(center: np.ndarray, size: np.ndarray, yaw: float) -> np.ndarray:
    """(5, 2) closed outline of a rectangle turned by ``yaw``."""
    half = np.asarray(size) / 2
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * half
    return corners @ planar_axes(yaw) + center


def plot_build(built: TwinBuild, out: Path) -> list[Path]:
    """``cloud.png`` (top and side views) and ``alignment.png`` (reference-point
    residuals, heights)."""
    plt = _pyplot()
    points, colors = built.levelled, built.model.colors / 255.0
    table = built.table
    near = np.linalg.norm(points[:, :2] - table.center, axis=1) < 1.5 * table.size.max()
    fig, (top, side) = plt.subplots(1, 2, figsize=(13, 5.5), width_ratios=(1.2, 1))
    top.scatter(points[near, 0], points[near, 1], s=1.5, c=colors[near])
    outline = _rectangle(table.center, table.size, table.yaw)
    top.plot(outline[:, 0], outline[:, 1], "k--", lw=1, label="table")
    for obj in built.objects:
        if obj.cluster.carved is not None:  # the footprint carved from silhouettes
            carved = obj.cluster.carved
            top.scatter(carved[:, 0], carved[:, 1], s=1, color="tab:olive", alpha=0.3)
        footprint = obj.cluster.points[:, :2]
        top.scatter(footprint[:, 0], footprint[:, 1], s=3)
        top.annotate(obj.name, obj.position, xytext=(6, 6), textcoords="offset points")
    for k, corners in enumerate(built.alignment.tag_outlines):
        top.fill(
            corners[:, 0], corners[:, 1], color="k", alpha=0.6, label="tags" if k == 0 else None
        )
    path = built.camera_path
    top.plot(path[:, 0], path[:, 1], "-", color="tab:blue", lw=1, label="camera path")
    for name, camera in built.cameras.items():
        top.plot(*camera.pos[:2], "^", color="tab:red", ms=9)
        top.annotate(name, camera.pos[:2], xytext=(6, -12), textcoords="offset points")
    top.plot(0, 0, "s", color="tab:gray", ms=9, label="robot base")
    top.set(xlabel="x (m)", ylabel="y (m)", title="top view, robot-base frame", aspect="equal")
    top.legend(loc="lower left", fontsize=8)
    side.scatter(points[near, 0], points[near, 2] - table.height, s=1.5, c=colors[near])
    side.axhline(0.0, color="k", ls="--", lw=1)
    for obj in built.objects:
        side.scatter(obj.cluster.points[:, 0], obj.cluster.points[:, 2] - table.height, s=3)
    side.set(
        xlabel="x (m)",
        ylabel="height above the table (m)",
        ylim=(-0.05, max(0.15, 1.3 * max(o.cluster.size[2] for o in built.objects))),
        title=f"side view (table plane tilted {table.tilt_deg:.2f} deg before levelling)",
    )
    fig.tight_layout()
    cloud = out / "cloud.png"
    fig.savefig(cloud, dpi=110)
    plt.close(fig)

    fig, (tag, heights) = plt.subplots(1, 2, figsize=(11, 4))
    alignment = built.alignment
    tag.bar(alignment.labels, 1000 * alignment.residuals)
    tag.set(
        ylabel="residual after alignment (mm)",
        title=f"{alignment.reference} ({alignment.views} views)",
    )
    rise = points[near, 2] - table.height
    heights.hist(rise[np.abs(rise) < 0.2], bins=120, color="tab:gray")
    heights.set_yscale("log")
    heights.set(xlabel="height above the fitted table (m)", ylabel="points", title="heights")
    fig.tight_layout()
    residual_plot = out / "alignment.png"
    fig.savefig(residual_plot, dpi=110)
    plt.close(fig)
    return [cloud, residual_plot]


def dropped_summary(dropped: list[DroppedCandidate]) -> str:
    """One line on the candidates not made objects, by cause ("": none)."""
    if not dropped:
        return ""
    causes = Counter(candidate.cause for candidate in dropped)
    named = ", ".join(cause if n == 1 else f"{cause} x{n}" for cause, n in causes.items())
    return f"{len(dropped)} candidate(s) not made objects ({named}): see report.md"


def dropped_lines(dropped: list[DroppedCandidate]) -> list[str]:
    """The report's table of the candidates not made objects, and why (none: no lines)."""
    if not dropped:
        return []
    lines = [
        "",
        "Not made objects (points above the table that the frames do not bear out):",
        "",
        "| x (m) | y (m) | size L x W x H (mm) | points | most likely | why |",
        "|---|---|---|---|---|---|",
    ]
    for candidate in dropped:
        size = " x ".join(f"{1000 * v:.0f}" for v in candidate.size)
        lines.append(
            f"| {candidate.center[0]:.3f} | {candidate.center[1]:.3f} | {size} | "
            f"{candidate.points} | {candidate.cause} | {candidate.reason} |"
        )
    return lines


def write_build_report(built: TwinBuild, out: Path, plots: list[Path]) -> Path:
    """``report.md``: what was kept, how well it aligned, what the scene holds, how long."""
    selection, model, alignment, table = built.selection, built.model, built.alignment, built.table
    lines = [
        f"# Twin build: {built.scene.name}",
        "",
        f"Scene spec: `{built.scene_path.name}` (compiles in MuJoCo; meshes in `meshes/`). "
        "Recording: `reconstruction.rrd` (`rerun reconstruction.rrd`).",
        "",
        "| step | result |",
        "|---|---|",
        f"| frames | {len(selection.paths)} kept of {selection.frames_in_clip} "
        f"({selection.dropped_blurry} blurry), camera travel {selection.travel:.2f} widths |",
        f"| structure from motion | {model.registered}/{model.frames} frames registered, "
        f"{len(model.points)} points{_mapping_note(model)} |",
        f"| alignment | {alignment.reference} ({', '.join(alignment.labels)}), seen in "
        f"{alignment.views} frames, residual {1000 * alignment.residual_m:.2f} mm RMS, "
        f"scale {alignment.to_base.scale:.4f} m/unit |",
        f"| table | top at {table.height:+.4f} m, {table.size[0]:.3f} x {table.size[1]:.3f} m, "
        f"yaw {np.degrees(table.yaw):+.1f} deg, tilt before levelling "
        f"{table.tilt_deg:.2f} deg; {_table_extent(table)} |",
    ]
    if built.size_ratio is not None:
        lines.append(f"| object sizes / task's | {built.size_ratio:.2f} (median) |")
    lines += [
        "",
        "## Objects",
        "",
        "| name | role | x (m) | y (m) | yaw (deg) | size L x W x H (mm) | convex parts | "
        "volume (cm^3) | mass (kg) | shape | evidence | confidence |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for obj in built.objects:
        size = " x ".join(f"{1000 * v:.0f}" for v in obj.cluster.size)
        shape = (
            obj.source
            if obj.fit_rms is None
            else (f"{Path(obj.source).name} (ICP {1000 * obj.fit_rms:.1f} mm RMS)")
        )
        mass = f"{obj.mass:.3f}" if obj.role == "manipulated" else "fixed"
        lines.append(
            f"| {obj.name} | {obj.role} | {obj.position[0]:.3f} | {obj.position[1]:.3f} | "
            f"{np.degrees(obj.yaw):+.1f} | {size} | {len(obj.shape.parts)} | "
            f"{1e6 * obj.shape.volume:.0f} | {mass} | {shape} | {obj.evidence.summary()} | "
            f"{obj.evidence.confidence} |"
        )
    doubtful = [obj for obj in built.objects if obj.evidence.doubts]
    if doubtful:
        lines += ["", "Where the evidence is thin:", ""]
        lines += [f"- {obj.name}: {'; '.join(obj.evidence.doubts)}." for obj in doubtful]
    lines += dropped_lines(built.dropped)
    if built.cameras:
        lines += [
            "",
            "## Cameras placed from photos",
            "",
            "| camera | position (m) | looks at (m) | fovy (deg) | image |",
            "|---|---|---|---|---|",
        ]
        for camera in built.cameras.values():
            pos = ", ".join(f"{v:.3f}" for v in camera.pos)
            lookat = ", ".join(f"{v:.3f}" for v in camera.lookat)
            lines.append(
                f"| {camera.name} | {pos} | {lookat} | {camera.fovy:.1f} | "
                f"{camera.width}x{camera.height} |"
            )
    if built.look is not None:
        lines += _look_section(built, out)
    lines += ["", "## Time", "", "| stage | seconds |", "|---|---|"]
    lines += [f"| {name} | {value:.1f} |" for name, value in built.seconds.items()]
    lines += [f"| total | {sum(built.seconds.values()):.1f} |", ""]
    lines += [f"![{plot.stem}]({plot.name})" for plot in plots]
    path = out / "report.md"
    write_text_atomic(path, "\n".join(lines) + "\n")
    return path


def write_build_rrd(built: TwinBuild, compiled: CompiledScene, path: Path) -> Path:
    """Point cloud, camera path, tags, placed cameras and the compiled scene's geometry."""
    recording = rr.RecordingStream("twinrl", recording_id=f"twin-build-{built.scene.digest}")
    recording.save(str(path))
    recording.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    recording.log(
        "world/reconstruction/points",
        rr.Points3D(built.levelled, colors=built.model.colors, radii=0.002),
        static=True,
    )
    recording.log(
        "world/reconstruction/camera_path",
        rr.LineStrips3D([built.camera_path], colors=[[60, 120, 220]]),
        static=True,
    )
    recording.log(
        "world/reconstruction/tags",
        rr.LineStrips3D([np.vstack([c, c[:1]]) for c in built.alignment.tag_outlines]),
        static=True,
    )
    _log_scene(recording, compiled)
    recording.flush()
    return path


def _log_scene(recording: rr.RecordingStream, compiled: CompiledScene) -> None:
    """Every visible geom of the compiled scene at its initial pose."""
    model = compiled.model
    data = mujoco.MjData(model)
    data.qpos[[model.joint(j).qposadr[0] for j in compiled.layout.arm_joints]] = (
        compiled.layout.home_qpos
    )
    mujoco.mj_forward(model, data)
    for g in range(model.ngeom):
        if model.geom_rgba[g, 3] == 0 or model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            continue
        name = model.geom(g).name or f"geom{g}"
        rotation = data.geom_xmat[g].reshape(3, 3)
        pose = rr.Transform3D(translation=data.geom_xpos[g], mat3x3=rotation)
        color = (255 * model.geom_rgba[g]).astype(np.uint8)
        size = model.geom_size[g]
        match int(model.geom_type[g]):
            case mujoco.mjtGeom.mjGEOM_MESH:
                mesh = model.geom_dataid[g]
                start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
                face_start, faces = model.mesh_faceadr[mesh], model.mesh_facenum[mesh]
                shape = rr.Mesh3D(
                    vertex_positions=model.mesh_vert[start : start + count],
                    triangle_indices=model.mesh_face[face_start : face_start + faces],
                    albedo_factor=color,
                )
            case mujoco.mjtGeom.mjGEOM_BOX:
                shape = rr.Boxes3D(half_sizes=[size], colors=[color], fill_mode="solid")
            case mujoco.mjtGeom.mjGEOM_SPHERE:
                shape = rr.Ellipsoids3D(half_sizes=[[size[0]] * 3], colors=[color])
            case mujoco.mjtGeom.mjGEOM_CAPSULE:
                shape = rr.Capsules3D(
                    lengths=[2 * size[1]],
                    radii=[size[0]],
                    colors=[color],
                    translations=[[0, 0, -size[1]]],
                )
            case mujoco.mjtGeom.mjGEOM_CYLINDER:
                shape = rr.Cylinders3D(lengths=[2 * size[1]], radii=[size[0]], colors=[color])
            case _:
                continue
        recording.log(f"world/scene/{name}", pose, static=True)
        recording.log(f"world/scene/{name}", shape, static=True)


def _table_extent(table: TablePlane) -> str:
    """Where the table's size comes from, and which of its edges were seen."""
    if table.extent_from != "frames":
        return "size from its SfM points only (the frames showed no table region): a lower bound"
    unseen = [side for side in SIDES if side not in table.sides_seen]
    if not unseen:
        return "size measured in the frames, every edge seen"
    return (
        f"size measured in the frames; edge {', '.join(unseen)} never seen beyond, so the "
        "table may reach further there"
    )


def _mapping_note(model: SparseModel) -> str:
    """How hard the mapper had to try, when it was more than once and one model."""
    notes = []
    if model.models > 1:
        notes.append(f"the largest of {model.models} models")
    if model.attempts > 1:
        notes.append(f"found at initialisation {model.attempts} (a more lenient first pair)")
    return f" ({'; '.join(notes)})" if notes else ""


def _look_section(built: TwinBuild, out: Path) -> list[str]:
    """The pictures the twin wears and how much it looks like frames they were not
    painted from, with one such frame beside the twin's renders (look.png)."""
    look, score = built.look, built.look_score
    lines = [
        "",
        "## The cell's look",
        "",
        f"Table top, objects and backdrop painted from {len(look.painters)} frames; "
        f"{100 * look.table_seen:.0f} % of the top was seen (the rest takes its colour).",
    ]
    if score is None:
        return lines
    Image.fromarray(score.example).save(out / "look.png")
    lines += [
        f"Judged on {score.frames} held-out frames, over the pixels where the twin shows "
        f"its table and objects ({100 * score.covered:.0f} % of a frame on average):",
        "",
        "| twin | PSNR (dB) | SSIM |",
        "|---|---|---|",
        f"| dressed | {score.psnr:.1f} | {score.ssim:.3f} |",
        f"| flat colours | {score.flat_psnr:.1f} | {score.flat_ssim:.3f} |",
        "",
        "![look](look.png)",
        "",
        "A held-out frame, the dressed twin and the flat twin from its pose.",
    ]
    return lines
