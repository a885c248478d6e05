"""Fit how the cell looks (the ``appearance`` effect) from logged images.

An image policy trained on twin renders sees the real cell's light and table colour;
where they differ, what it learned in the twin does not carry over. The twin renders
sampled frames at the *measured* state (as :mod:`twinrl_sim.gap.camera` does) from
every logged camera, and the light intensity and the table's colour offset are fitted
so that the renders match the logged images in colour (box-averaged RGB, not
standardised: brightness is what is fitted here).

The fit is ``mujoco.sysid``'s: one :class:`sysid.Parameter` (light scale, table tint
RGB) whose modifier applies the effect to a copy of the twin's ``MjSpec``;
:func:`sysid.optimize` on the colour residual; :func:`sysid.calculate_intervals`.
"""

from __future__ import annotations

import mujoco
import numpy as np
from mujoco import sysid

from twinrl_sim.build import build_mjspec
from twinrl_sim.effects import apply_appearance, apply_effects
from twinrl_sim.errors import TwinError
from twinrl_sim.gap.camera import Frames, colours, render_measured
from twinrl_sim.gap.identify import least_squares
from twinrl_sim.spec import SceneSpec

LIGHT_STEP = 0.05  # light scale per optimiser unit
TINT_STEP = 0.02  # table colour (0-1) per optimiser unit
LIGHT_RANGE = (0.2, 3.0)
TINT_RANGE = 0.5
FD_STEP = 0.5  # optimiser units: 2.5 % light, 0.01 colour, above 8-bit quantisation
MAX_ITERS = 15


class AppearanceFit:
    """The twin of ``scene`` (plus ``fixed`` effects) rendering ``frames`` (one
    :class:`Frames` per camera, in :func:`colours` form) with its appearance
    adjustable: a ``mujoco.sysid`` residual over all frames of all cameras.

    An ``appearance`` already in the scene or in ``fixed`` is where the fit starts
    (the fitted one replaces it)."""

    def __init__(
        self,
        scene: SceneSpec,
        frames: list[Frames],
        noise: float,
        *,
        fixed: dict[str, dict] | None = None,
    ) -> None:
        if not frames:
            raise TwinError("the appearance fit needs logged images of at least one camera")
        self.frames, self.noise = frames, noise
        fixed = dict(fixed or {})
        current = fixed.pop("appearance", None) or scene.effects.get("appearance")
        others = {k: v for k, v in scene.effects.items() if k != "appearance"}
        self.spec, self.layout = build_mjspec(scene.model_copy(update={"effects": others}))
        if fixed:
            apply_effects(self.spec, self.layout, fixed)
        self.model = self.spec.copy().compile()
        self.data = mujoco.MjData(self.model)
        self.renderers = {
            f.camera: mujoco.Renderer(self.model, height=f.size[0], width=f.size[1]) for f in frames
        }
        self.start = (
            np.zeros(4)
            if current is None
            else np.r_[
                (current["light_scale"] - 1) / LIGHT_STEP,
                np.asarray(current["table_tint"], float) / TINT_STEP,
            ]
        )
        low = np.r_[(LIGHT_RANGE[0] - 1) / LIGHT_STEP, [-TINT_RANGE / TINT_STEP] * 3]
        high = np.r_[(LIGHT_RANGE[1] - 1) / LIGHT_STEP, [TINT_RANGE / TINT_STEP] * 3]
        self.params = sysid.ParameterDict()
        self.params.add(
            sysid.Parameter(
                "appearance",
                nominal=self.start.copy(),
                min_value=low,
                max_value=high,
                modifier=lambda spec, p: apply_appearance(
                    spec, self.layout, **self.effect_at(p.value)
                ),
            )
        )

    @staticmethod
    def effect_at(x: np.ndarray) -> dict:
        """The appearance effect at ``x`` in effects-file form."""
        x = np.asarray(x, float)
        return {
            "light_scale": float(1 + x[0] * LIGHT_STEP),
            "table_tint": (x[1:4] * TINT_STEP).tolist(),
        }

    @staticmethod
    def interval_at(half_width: np.ndarray) -> dict:
        half_width = np.asarray(half_width, float)
        return {
            "light_scale": float(half_width[0] * LIGHT_STEP),
            "table_tint": (half_width[1:4] * TINT_STEP).tolist(),
        }

    def _restyle(self, x: np.ndarray) -> None:
        """Give the compiled model the colours of the twin at ``x`` (lights, materials,
        geoms and textures, re-uploaded to each renderer)."""
        params = self.params.copy()
        params.update_from_vector(np.asarray(x, float))
        styled = sysid.apply_param_modifiers_spec(params, self.spec.copy()).compile()
        m = self.model
        m.light_diffuse[:] = styled.light_diffuse
        m.geom_rgba[:] = styled.geom_rgba
        m.mat_rgba[:] = styled.mat_rgba
        if not np.array_equal(m.tex_data, styled.tex_data):
            m.tex_data[:] = styled.tex_data
            for renderer in self.renderers.values():  # mujoco.Renderer has no public upload
                renderer._gl_context.make_current()
                for texture in range(m.ntex):
                    mujoco.mjr_uploadTexture(m, renderer._mjr_context, texture)

    def render(self, x: np.ndarray) -> list[np.ndarray]:
        """Each camera's frames as the twin renders them at ``x`` (:func:`colours` form)."""
        self._restyle(x)
        return [
            colours(
                render_measured(self.model, self.data, self.renderers[f.camera], self.layout, f)
            )
            for f in self.frames
        ]

    def residuals(self, x: np.ndarray | None = None) -> np.ndarray:
        """All frames' colour residuals (flat) in image-noise units at ``x`` (default:
        where the fit starts)."""
        x = self.start if x is None else x
        rendered = self.render(x)
        return (
            np.concatenate(
                [(f.images - r).ravel() for f, r in zip(self.frames, rendered, strict=True)]
            ).astype(np.float64)
            / self.noise
        )

    def _residual_fn(self, x: np.ndarray, _params: sysid.ParameterDict):
        """sysid's residual signature; the finite-difference Jacobian passes its points
        as the columns of ``x``."""
        x = np.asarray(x, float)
        if x.ndim == 1:
            return [self.residuals(x)], None, None
        return [np.stack([self.residuals(c) for c in x.T], axis=1)], None, None

    def fit(self) -> tuple[np.ndarray, np.ndarray, int]:
        """Least-squares fit: (x, 95 % half-widths, iterations) in optimiser units."""
        params, result, iterations = least_squares(
            self.params, self._residual_fn, eps=FD_STEP, xtol=1e-3, max_iters=MAX_ITERS
        )
        x = params.as_vector()
        _, half_width = sysid.calculate_intervals([self.residuals(x)], result.jac)
        return x, np.asarray(half_width), iterations

    def close(self) -> None:
        for renderer in self.renderers.values():
            renderer.close()
