"""Objects of the twin build whole and only where they stand (issue 52): footprint
clustering, the silhouettes' hull and its top, and the candidates that are dropped."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from twinrl_sim.reconstruct.candidates import (
    HIGHLIGHT,
    REFLECTION,
    SEEN_THROUGH,
    SHADOW,
    STRAY,
    TABLE_TEXTURE,
    TAG_SHEET,
    judge_candidates,
    name_cause,
)
from twinrl_sim.reconstruct.evidence import ObjectEvidence, bound_one_sided, weigh_evidence
from twinrl_sim.reconstruct.pipeline import build_twin
from twinrl_sim.reconstruct.report import dropped_lines, dropped_summary
from twinrl_sim.reconstruct.segment import (
    ObjectCluster,
    TablePlane,
    describe_cluster,
    find_objects,
)
from twinrl_sim.reconstruct.settings import BuildSettings
from twinrl_sim.reconstruct.silhouette import Hull, _carving, lab_colours, object_colours
from twinrl_sim.reconstruct.synthetic import (
    CLUTTERED_SCENE,
    LOW_WALK,
    OFFICE_TAG,
    render_walkthrough,
)

TABLE = TablePlane(0.0, np.zeros(2), np.ones(2), 0.0, np.full(3, 0.93), 0.0, 100)
WHITE, DARK, LABEL = np.full(3, 0.93), np.array([0.12, 0.1, 0.08]), np.array([0.9, 0.75, 0.3])


def _column(rng, xy, radius, low, high, n) -> np.ndarray:
    angle, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(low, high, n)
    return np.c_[xy[0] + radius * np.cos(angle), xy[1] + radius * np.sin(angle), z]


def test_a_labels_points_and_a_caps_are_one_object_however_tall():
    rng = np.random.default_rng(0)
    # A bottle whose plain glass gave no points between its label and its cap, and a
    # box 40 cm tall: each is one object, with all its points (the box's top is left to
    # the silhouettes: points up its sides do not say where a top surface is).
    bottle = np.vstack(
        [
            _column(rng, (0.3, 0.1), 0.035, 0.03, 0.11, 120),
            _column(rng, (0.3, 0.1), 0.015, 0.21, 0.23, 30),
        ]
    )
    box = _column(rng, (0.5, -0.2), 0.04, 0.01, 0.4, 200)
    points = np.vstack([bottle, box])
    objects = find_objects(points, np.full((len(points), 3), 128.0), TABLE)
    assert len(objects) == 2
    tall, short = sorted(objects, key=lambda o: -o.size[2])
    assert tall.points[:, 2].max() > 0.35 and np.linalg.norm(tall.center[:2] - [0.5, -0.2]) < 0.02
    assert short.size[2] == pytest.approx(0.23, abs=0.015)
    assert np.linalg.norm(short.center[:2] - [0.3, 0.1]) < 0.01


def test_a_dark_labelled_object_has_colours_to_carve_and_a_white_one_none():
    rng = np.random.default_rng(0)
    colours = np.vstack([DARK + rng.normal(0, 0.02, (60, 3)), LABEL + rng.normal(0, 0.02, (40, 3))])
    found = object_colours(np.clip(colours, 0, 1), WHITE)
    for colour in (DARK, LABEL):
        assert np.linalg.norm(found - lab_colours(colour), axis=1).min() < 10
    assert len(object_colours(WHITE + rng.normal(0, 0.01, (50, 3)), WHITE)) == 0


def _hull(height: float, seen_above: bool, elevation_deg: float) -> Hull:
    """The hull of a 7 cm cylinder ``height`` tall standing at the origin, as votes on the
    carving's grid would make it (every view agreeing), seen from cameras 1 m away all
    round at ``elevation_deg`` over its top."""
    rng = np.random.default_rng(0)
    points = _column(rng, (0.0, 0.0), 0.035, 0.01, 0.5 * height, 100)
    cluster = ObjectCluster(np.zeros(3), np.ones(3), 0.0, DARK, points)
    carving = _carving(cluster, lab_colours(LABEL), TABLE, lambda p: p)
    views = 20
    inside = np.linalg.norm(carving.grid[:, :2], axis=1) <= 0.035
    inside &= carving.grid[:, 2] <= height
    carving.seen[:] = views
    if not seen_above:
        carving.seen[carving.grid[:, 2] > height] = 0  # out of every frame
    carving.inside[:] = views * inside
    angle = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    rise = math.tan(math.radians(elevation_deg))
    cameras = np.c_[np.cos(angle), np.sin(angle), np.full(24, height + rise)]
    return carving.hull(cameras, rng)


def test_the_hulls_top_is_where_the_silhouettes_end_and_a_lower_bound_when_unseen():
    seen = _hull(0.2, seen_above=True, elevation_deg=5.0)
    assert seen.outlines and seen.top == pytest.approx(0.2, abs=0.01) and seen.top_seen
    assert seen.trusted_top == seen.top
    assert np.all(np.linalg.norm(seen.footprint, axis=1) < 0.04)
    unseen = _hull(0.2, seen_above=False, elevation_deg=5.0)
    assert not unseen.top_seen and unseen.top == pytest.approx(0.2, abs=0.01)
    # Seen steeply from above, a hull overshoots the top: its top is not trusted.
    assert _hull(0.05, seen_above=True, elevation_deg=60.0).trusted_top is None


def test_an_object_whose_top_was_not_seen_has_its_height_said_to_be_a_lower_bound():
    class NoFrames:  # a walk whose frames are not needed to judge the top
        def walk_images(self) -> list:
            return []

    class Identity:
        def invert(self, points: np.ndarray) -> np.ndarray:
            return points

    rng = np.random.default_rng(1)
    points = _column(rng, (0.0, 0.0), 0.03, 0.0, 0.23, 200)
    size = np.array([0.07, 0.07, 0.23])
    whole = ObjectCluster(np.zeros(3), size, 0.0, DARK, points, carved=np.zeros((4, 2)))
    cut = ObjectCluster(
        np.zeros(3), size, 0.0, DARK, points, carved=np.zeros((4, 2)), top_seen=False
    )
    said = weigh_evidence(cut, NoFrames(), Identity()).doubts
    assert any("its height, 230 mm, is a lower bound" in doubt for doubt in said)
    assert not any("lower bound" in d for d in weigh_evidence(whole, NoFrames(), Identity()).doubts)


def test_candidates_without_silhouettes_are_dropped_with_the_reason():
    rng = np.random.default_rng(0)
    points = _column(rng, (0.0, 0.0), 0.02, 0.0, 0.04, 48)
    stray = ObjectCluster(np.zeros(3), np.array([0.066, 0.022, 0.038]), 0.0, DARK, points)
    clear = ObjectCluster(np.zeros(3), np.ones(3), 0.0, WHITE, points, outline=2)
    mark = ObjectCluster(np.zeros(3), np.ones(3), 0.0, WHITE, points)
    real = ObjectCluster(np.zeros(3), np.ones(3), 0.0, DARK, points)
    empty = Hull(None, False, None, False, 0.0)
    whole = Hull(np.zeros((5, 2)), True, 0.04, True, 0.0)
    kept, dropped = judge_candidates([stray, clear, mark, real], [empty, None, None, whole], TABLE)
    assert kept == [1, 3]
    assert [d.points for d in dropped] == [48, 48]
    assert "no silhouette holds" in dropped[0].reason and "too few" in dropped[1].reason
    table = "\n".join(dropped_lines(dropped))
    assert "| 0.000 | 0.000 | 66 x 22 x 38 | 48 | seen through a clear object |" in table
    assert dropped_lines([]) == []
    shadow = replace(dropped[1], cause=SHADOW)
    assert dropped_summary([*dropped, shadow]) == (
        "3 candidate(s) not made objects (seen through a clear object x2, a shadow): see report.md"
    )
    assert dropped_summary([]) == ""


def _patch(xy, colour, n=30, seed=0) -> ObjectCluster:
    """A few points just over the table at ``xy``, every one of them ``colour``."""
    points = _column(np.random.default_rng(seed), xy, 0.01, 0.005, 0.012, n)
    return ObjectCluster(
        np.array([*xy, 0.006]),
        np.array([0.02, 0.02, 0.012]),
        0.0,
        colour,
        points,
        point_colors=np.tile(colour, (n, 1)),
    )


def _standing(rng, xy, width, height, colour, outline=0) -> ObjectCluster:
    """An object kept by the build: a column of points ``width`` across at ``xy``."""
    points = _column(rng, xy, width / 2, 0.0, height, 200)
    return ObjectCluster(
        np.array([*xy, height / 2]), np.array([width, width, height]), 0.0, colour, points,
        outline=outline, point_colors=np.tile(colour, (200, 1)),
    )  # fmt: skip


def test_each_dropped_candidate_is_named_by_what_it_most_likely_is():
    rng = np.random.default_rng(3)
    bottle = _standing(rng, (0.4, 0.0), 0.07, 0.23, DARK)  # a dark bottle
    glass = _standing(rng, (0.1, 0.3), 0.08, 0.12, WHITE, outline=3)  # a clear glass
    tag = np.array([[-0.05, -0.05, 0], [0.05, -0.05, 0], [0.05, 0.05, 0], [-0.05, 0.05, 0]])
    grey, glare = WHITE * 0.55, np.full(3, 0.99)
    cases = {
        TAG_SHEET: _patch((0.09, 0.0), DARK),  # past the tag's black, on its white sheet
        SEEN_THROUGH: _patch((0.11, 0.31), LABEL),
        HIGHLIGHT: _patch((0.3, -0.3), glare),
        SHADOW: _patch((0.48, 0.0), grey),  # just behind the bottle, the table grey
        REFLECTION: _patch((0.4, -0.09), DARK),  # in front of the bottle, its colour
        TABLE_TEXTURE: _patch((-0.3, 0.3), WHITE * 0.97),
        STRAY: _patch((-0.3, -0.3), LABEL),
    }
    for cause, patch in cases.items():
        named, seen = name_cause(patch, TABLE, [tag], [bottle, glass])
        assert named == cause, (cause, seen)
    # A shadow on its own is a shadow still; the tag's sheet only where a tag lies.
    assert name_cause(_patch((-0.3, 0.3), grey), TABLE, [], [])[0] == SHADOW
    assert name_cause(_patch((0.09, 0.0), LABEL), TABLE, [], [bottle])[0] == STRAY
    # The reason says what was seen, for the person reading the report.
    _, seen = name_cause(cases[SHADOW], TABLE, [tag], [bottle, glass])
    assert "darker" in seen and "from object 1" in seen


def test_an_object_seen_from_one_side_is_no_deeper_than_it_is_wide():
    """A bottle (71 mm across) filmed from one side: its points sit on the half facing
    the phone, triangulated 2 cm off along the view (a narrow baseline), which made it
    149 mm deep. Its depth is bounded by its width across; seen all round, or carved
    from silhouettes, it is left as it is."""
    rng = np.random.default_rng(1)
    angle, z = rng.uniform(-np.pi / 2, np.pi / 2, 400), rng.uniform(0.01, 0.23, 400)
    front = np.c_[0.33 + 0.0355 * np.cos(angle), 0.14 + 0.0355 * np.sin(angle), z]
    front[:, 0] += rng.normal(0.0, 0.02, len(front))  # the views look along -x
    cluster = describe_cluster(front, DARK, TABLE)
    assert cluster.size[0] > 0.1  # as deep as the error made it
    one_side = ObjectEvidence(93, 42.0, len(front), False, (), np.array([-1.0, 0.0]))
    bounded = bound_one_sided(cluster, one_side, None, TABLE)
    assert bounded.size[:2] == pytest.approx([0.071, 0.071], rel=0.1)
    assert bounded.size[2] == pytest.approx(cluster.size[2])
    assert np.linalg.norm(bounded.center[:2] - cluster.center[:2]) < 0.01
    all_round = ObjectEvidence(93, 120.0, len(front), False, (), np.array([-1.0, 0.0]))
    assert bound_one_sided(cluster, all_round, None, TABLE) is cluster
    carved = describe_cluster(front, DARK, TABLE, front[:, :2])
    assert bound_one_sided(carved, one_side, None, TABLE) is carved


def test_an_object_seen_from_one_side_is_no_wider_across_the_view_than_its_hulls_base():
    """A purple box (100 x 70 mm, turned so that it spans 87 mm across the view) filmed
    from one side: stray matches on the clutter behind it spread its points 19 cm across
    the view. Its hull's base, seen against the table, spans the box alone; the points
    outside that band go, and the depth is bounded by what is left. A hull whose base
    misses most of the points leaves them."""
    rng = np.random.default_rng(2)
    yaw, half = 0.4, np.array([0.05, 0.035])
    turn = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    faces = rng.uniform(-1, 1, (300, 2)) * half
    faces[np.arange(300) % 2 == 0, 0] = half[0]  # the two faces towards the phone
    faces[np.arange(300) % 2 == 1, 1] = half[1]
    box = np.c_[np.array([0.42, -0.2]) + faces @ turn.T, rng.uniform(0.01, 0.33, 300)]
    box[:, 0] += rng.normal(0.0, 0.03, 300)  # the views look along -x: depth is error
    strays = np.c_[
        rng.uniform(0.36, 0.48, 40), rng.uniform(-0.3, -0.1, 40), rng.uniform(0.1, 0.3, 40)
    ]
    purple = np.array([0.55, 0.2, 0.6])
    cluster = describe_cluster(np.vstack([box, strays]), purple, TABLE)
    assert cluster.size[:2].max() > 0.17
    one_side = ObjectEvidence(93, 43.0, len(cluster.points), False, (), np.array([-1.0, 0.0]))
    corners = np.array([[sx, sy] for sx in (-1, 1) for sy in (-1, 1)]) * half @ turn.T
    low, high = corners.min(axis=0) + [0.42, -0.2], corners.max(axis=0) + [0.42, -0.2]
    grid = np.stack(
        np.meshgrid(*(np.arange(a, b, 0.003) for a, b in zip(low, high, strict=True))), -1
    )
    base = grid.reshape(-1, 2)  # the columns over the box's bounding rectangle
    hull = Hull(base, False, None, False, 0.0, chromatic=True, base=base)
    bounded = bound_one_sided(cluster, one_side, hull, TABLE)
    across = float(np.ptp(corners[:, 1]))  # 87 mm
    assert bounded.size[:2].max() < 1.15 * across
    assert np.linalg.norm(bounded.center[:2] - [0.42, -0.2]) < 0.02
    assert bounded.size[2] == pytest.approx(cluster.size[2], abs=0.01)
    aside = Hull(base + [0.0, 0.3], False, None, False, 0.0, chromatic=True, base=base + [0.0, 0.3])
    for unsure in (None, aside):
        assert bound_one_sided(cluster, one_side, unsure, TABLE).size[:2].max() > 0.15


@pytest.mark.slow
@pytest.mark.parametrize(
    "seed",
    [0, pytest.param(1, marks=pytest.mark.long)],  # seed 1 beyond CI's time
)
def test_a_dark_bottle_and_a_box_taller_than_the_phone_are_built_whole(tmp_path, seed):
    """Filmed low over a glossy table with clutter behind (issue 52): a dark bottle in a
    label and a box taller than the phone is held, each within 10 % of its height and
    3 cm of where it stands, and no other object. Seed 1's walk shakes less (its view
    shifts 0.22 image widths in all), and was refused as a camera that barely moves."""
    walk = render_walkthrough(
        CLUTTERED_SCENE, tmp_path / "frames", tags=OFFICE_TAG, settings=LOW_WALK, seed=seed
    )
    settings = BuildSettings(
        tag_size=0.14,
        tag_pose=tuple(walk.tag_poses[12]),
        tag_id=12,
        frames=93,
        look=False,
        seed=seed,
    )
    built = build_twin(walk.video, tmp_path / "cell", settings)
    assert len(built.objects) == len(CLUTTERED_SCENE.objects)
    for truth in CLUTTERED_SCENE.objects:
        obj = min(built.objects, key=lambda o: np.linalg.norm(o.position - truth.pos[:2]))
        assert np.linalg.norm(obj.position - truth.pos[:2]) < 0.03
        assert obj.cluster.size[2] == pytest.approx(2 * truth.pos[2], rel=0.1)
