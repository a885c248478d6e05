"""How much the twin looks like the cell: renders from held-out frames' poses against
the frames, over the pixels where the twin shows its table and objects (the arm is left
out: its look comes from its model, not from the frames), dressed and in flat colours."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from PIL import Image
from skimage.metrics import structural_similarity

from twinrl_sim.build import compile_scene, look_at_quat
from twinrl_sim.reconstruct.look import FrameView, Lighting
from twinrl_sim.spec import CameraSpec, SceneSpec

HIDDEN_GROUP = 5  # the arm's geoms while judging
JUDGE_CAMERA = "look_judge"  # the camera added to a judged scene, moved to each frame
MIN_PIXELS = 100  # a held-out frame showing fewer of the twin's pixels is not judged
GAIN_VIEWS = 6  # frames the twin's lighting is measured from
PROBE_GREYS = (0.2, 0.6)  # flat greys rendered to measure it (bright ones would clip)
MIN_GAIN = 0.05  # a surface the lights hardly reach is not made a hundred times brighter


@dataclass(frozen=True)
class LookScore:
    """Masked PSNR (dB) and SSIM of twin renders against held-out frames."""

    frames: int
    psnr: float  # dressed twin
    ssim: float
    flat_psnr: float  # the same twin in flat colours
    flat_ssim: float
    covered: float  # mean share of each frame's pixels the mask keeps
    example: np.ndarray  # (H, 3W, 3): a held-out frame, the dressed twin, the flat twin


def flat_colours(scene: SceneSpec) -> SceneSpec:
    """``scene`` without its pictures: table, objects and room in plain colours."""
    return _restyled(scene, {"image": None}, {"look": None})


def _restyled(scene: SceneSpec, table: dict, objects: dict) -> SceneSpec:
    """``scene`` with ``table`` and every object's fields updated, and no backdrop."""
    return scene.model_copy(
        update={
            "table": scene.table.model_copy(update=table),
            "objects": [o.model_copy(update=objects) for o in scene.objects],
            "backdrop": None,
        }
    )


def score_look(scene: SceneSpec, judges: list[FrameView]) -> LookScore:
    """Render ``scene`` (with its pictures) and its flat-coloured copy from each judging
    frame's pose and compare them with the frame where the twin shows table or objects."""
    dressed = _Renders(scene)
    flat = _Renders(flat_colours(scene))
    scores, shares, example, best = [], [], None, 0.0
    try:
        for view in judges:
            (image, shown), (plain, _) = dressed.render(view), flat.render(view)
            mask = dressed.judged[shown]
            shares.append(mask.mean())
            if mask.sum() < MIN_PIXELS:  # the frame hardly shows the table
                continue
            scores.append(
                [*_similarity(view.image, image, mask), *_similarity(view.image, plain, mask)]
            )
            if mask.mean() > best:  # the example: the frame showing most of the twin
                example, best = np.hstack([view.image, image, plain]), mask.mean()
    finally:
        dressed.close()
        flat.close()
    if not scores:
        raise ValueError("no held-out frame shows the table")
    psnr, ssim, flat_psnr, flat_ssim = np.mean(scores, axis=0)
    return LookScore(
        frames=len(scores),
        psnr=float(psnr),
        ssim=float(ssim),
        flat_psnr=float(flat_psnr),
        flat_ssim=float(flat_ssim),
        covered=float(np.mean(shares)),
        example=example,
    )


def twin_lighting(
    scene: SceneSpec, views: list[FrameView], *, dressed: bool
) -> dict[str, Lighting]:
    """The twin's lighting of its table and each object, as seen from ``views``: the
    twin in one flat grey, for two greys, rendered; per surface the line through the two
    (median over the views). ``dressed``: the grey is a picture, which MuJoCo lights
    differently from a plain colour (a picture modulates the lit white, clipped at 1),
    and an object then shows its surface mesh rather than its convex parts."""
    low, high = PROBE_GREYS
    rendered = [_grey_renders(scene, views, grey, dressed) for grey in PROBE_GREYS]
    lighting = {}
    for owner in set(rendered[0]) & set(rendered[1]):
        dark, light = np.median(rendered[0][owner]), np.median(rendered[1][owner])
        gain = max((light - dark) / (high - low), MIN_GAIN)
        lighting[owner] = Lighting(float(gain), float(dark - gain * low))
    return lighting


def _grey_renders(
    scene: SceneSpec, views: list[FrameView], grey: float, dressed: bool
) -> dict[str, list]:
    """Per surface (table, objects): its median brightness (0-1) in each view, the twin
    all in ``grey``: a picture if ``dressed``, else a plain colour."""
    with tempfile.TemporaryDirectory() as folder:
        picture = Path(folder) / "grey.png"
        Image.fromarray(np.full((8, 8, 3), round(255 * grey), np.uint8)).save(picture)
        plain = (grey, grey, grey, 1.0)
        table = {"image": picture} if dressed else {"image": None, "rgba": plain}
        objects = {"look": picture} if dressed else {"look": None, "rgba": plain}
        renders = _Renders(_restyled(scene, table, objects))
    seen: dict[str, list[float]] = {}
    try:
        for view in views[:: max(1, len(views) // GAIN_VIEWS)]:
            image, shown = renders.render(view)
            owners = renders.owner[shown]
            for owner in set(owners.ravel()) - {""}:
                pixels = image[owners == owner].mean(axis=1)
                if len(pixels) >= MIN_PIXELS:
                    seen.setdefault(owner, []).append(float(np.median(pixels)) / 255)
    finally:
        renders.close()
    return seen


def _similarity(frame: np.ndarray, render: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """PSNR (dB, 8-bit) and mean SSIM over ``mask``."""
    error = (frame[mask].astype(float) - render[mask].astype(float)) ** 2
    psnr = 10 * np.log10(255.0**2 / max(error.mean(), 1e-12))
    _, local = structural_similarity(frame, render, channel_axis=2, data_range=255, full=True)
    return float(psnr), float(local[mask].mean())


class _Renders:
    """One scene rendered from frames' poses, through a camera of its own moved to each."""

    def __init__(self, scene: SceneSpec) -> None:
        judge = CameraSpec(name=JUDGE_CAMERA, pos=(0.0, 0.0, 1.0))  # placed per frame
        compiled = compile_scene(scene.model_copy(update={"cameras": [*scene.cameras, judge]}))
        self.model = model = compiled.model
        self.data = mujoco.MjData(model)
        mujoco.mj_forward(model, self.data)
        shown = {"world", "table", *scene.object_names}
        # Per geom id (and -1, nothing, last): the body it belongs to, where judged.
        self.owner = np.full(model.ngeom + 1, "", dtype=object)
        for geom in range(model.ngeom):
            body = model.body(model.geom_bodyid[geom]).name or "world"
            if body not in shown:
                model.geom_group[geom] = HIDDEN_GROUP
            elif body != "world":
                self.owner[geom] = body
        self.judged = self.owner != ""
        self.option = mujoco.MjvOption()
        self.option.geomgroup[HIDDEN_GROUP] = 0
        self.camera = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, JUDGE_CAMERA)
        self.renderers: dict[tuple[int, int], mujoco.Renderer] = {}

    def render(self, view: FrameView) -> tuple[np.ndarray, np.ndarray]:
        """The twin's image from ``view``'s pose and the geom each pixel shows (-1: none)."""
        height, width = view.image.shape[:2]
        if (height, width) not in self.renderers:
            self.renderers[height, width] = mujoco.Renderer(self.model, height, width)
        renderer = self.renderers[height, width]
        rotation = view.world_to_camera[:3, :3]  # rows: the camera's x right, y down, z ahead
        self.model.cam_pos[self.camera] = view.centre
        self.model.cam_quat[self.camera] = look_at_quat(
            view.centre, view.centre + rotation[2], -rotation[1]
        )
        self.model.cam_fovy[self.camera] = np.degrees(
            2 * np.arctan(height / 2 / view.intrinsics[1, 1])
        )
        mujoco.mj_forward(self.model, self.data)
        renderer.update_scene(self.data, self.camera, self.option)
        image = renderer.render().copy()
        renderer.enable_segmentation_rendering()
        renderer.update_scene(self.data, self.camera, self.option)
        segments = renderer.render()
        renderer.disable_segmentation_rendering()
        is_geom = (segments[..., 1] == mujoco.mjtObj.mjOBJ_GEOM) & (segments[..., 0] >= 0)
        return image, np.where(is_geom, segments[..., 0], -1)

    def close(self) -> None:
        for renderer in self.renderers.values():
            renderer.close()
