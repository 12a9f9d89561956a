"""Skeleton layouts: learned joint-angle ranges (from real recorded motion), thumb definition."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from benchmark_scripts import load_benchmark

from handanno_core.skeleton import ICVL16, MSRA21, NYU14, get_skeleton
from handanno_core.synth import gesture_library, local_pose, make_hand_model

REPO = Path(__file__).resolve().parents[1]
REAL = next(
    (
        p
        for p in (REPO.parent / "shared/data/real-motion", Path("/work/shared/data/real-motion"))
        if p.is_dir()
    ),
    None,
)
needs_real = pytest.mark.skipif(REAL is None, reason="shared/data/real-motion not available")


def _learn_module():
    return load_benchmark("learn_angle_ranges")


@needs_real
@pytest.mark.parametrize("layout", ["msra21", "nyu14", "icvl16"])
def test_learned_ranges_contain_the_motion_they_were_learned_from(layout):
    """>= 99 % of every joint's flexion and abduction on the real-motion frames the table was
    learned from lie inside the learned range (mirrored labels measured as the table says)."""
    import json

    learn = _learn_module()
    sk = get_skeleton(layout)
    poses = learn.load_layout(layout, REAL)
    table = json.loads((REPO / "handanno_core/data/angle_ranges.json").read_text())["layouts"]
    mirrored = table[layout]["mirrored"]
    flex, abd = sk.joint_angles(poses, right_hand=not mirrored)
    if mirrored:
        abd = -abd
    fl, ab = sk.learned_angle_ranges()
    assert np.all(np.isfinite(fl)) and len(fl) == len(sk.angle_joints)
    inside_f = np.mean((flex >= fl[:, 0] - 1e-6) & (flex <= fl[:, 1] + 1e-6), axis=0)
    inside_a = np.mean((abd >= ab[:, 0] - 1e-6) & (abd <= ab[:, 1] + 1e-6), axis=0)
    assert inside_f.min() >= 0.99 and inside_a.min() >= 0.99, (inside_f, inside_a)
    # and the ranges are not vacuous: every flexion range is narrower than a full turn
    assert np.all(np.ptp(fl, axis=1) < 330.0)


def _open_hand(params_edit=None):
    model = make_hand_model(0)
    params = gesture_library(model)["open"].copy()
    if params_edit:
        for i, v in params_edit.items():
            params[i] = v
    return local_pose(model, params)[0]


def test_reversed_finger_is_rejected_and_natural_poses_are_not():
    """A finger bent backwards by 60 degrees at the PIP (impossible) lies far outside the
    learned ranges; the same hand with natural angles does not."""
    natural = _open_hand()
    assert np.max(MSRA21.angle_range_violation_deg(natural)) < 1.0
    pip = {i: 4 * i + 2 for i in range(4)}  # synth parameter index of each finger's PIP flexion
    names = ("index_pip", "middle_pip", "ring_pip", "little_pip")
    for finger, name in enumerate(names):
        bent = _open_hand({pip[finger]: -60.0})
        flex, _ = MSRA21.joint_angles(bent)
        a = list(MSRA21.angle_joints).index(MSRA21.joint_names.index(name))
        assert flex[a] == pytest.approx(-60.0, abs=0.5)
        v = MSRA21.angle_range_violation_deg(bent)
        assert v[a] > 40.0, (name, v[a])
        assert np.sum(v > 1.0) == 1  # only the reversed joint


def test_angle_ranges_widen_the_anatomical_limits_and_mirror_for_a_left_hand():
    fl_lim, ab_lim = MSRA21.angle_limits()
    fl, ab = MSRA21.angle_ranges()
    assert np.all(fl[:, 0] <= fl_lim[:, 0]) and np.all(fl[:, 1] >= fl_lim[:, 1])
    assert np.all(ab[:, 0] <= ab_lim[:, 0]) and np.all(ab[:, 1] >= ab_lim[:, 1])
    fl_left, ab_left = MSRA21.angle_ranges(right_hand=False)
    np.testing.assert_array_equal(fl_left, fl)
    np.testing.assert_array_equal(ab_left, -ab[:, ::-1])


def test_thumb_follows_the_msra_fpha_definition():
    """The first thumb joint is the CMC side: a child of the wrist, with the thumb's three
    further joints below it; the FPHA mapping sends FPHA's TMCP there."""
    from handanno_core.skeleton import FPHA_TO_MSRA21

    cmc = MSRA21.joint_names.index("thumb_cmc")
    assert MSRA21.parent_array[cmc] == MSRA21.root
    assert FPHA_TO_MSRA21[cmc] == 1  # FPHA: wrist, TMCP, ...
    assert sorted(FPHA_TO_MSRA21) == list(range(21))
    chain = [cmc]
    while len(MSRA21.children(chain[-1])):
        chain.append(int(MSRA21.children(chain[-1])[0]))
    assert [MSRA21.joint_names[k] for k in chain] == [
        "thumb_cmc",
        "thumb_mcp",
        "thumb_ip",
        "thumb_tip",
    ]


@pytest.mark.parametrize("sk", [NYU14, ICVL16])
def test_layout_surface_groups_anchor_the_tips(sk):
    g = sk.surface_groups()
    assert np.all(g[list(sk.fingertips)] == -1)
    assert g[sk.root] == 0 and np.all(g[[k for k in range(sk.num_joints) if k != sk.root]] != 0)
