"""Synthetic takes: determinism, ground-truth consistency, occlusion, blinks, rendering."""

import numpy as np
import pytest

from carapost.core.camera import camera_centre, project
from carapost.synth import SynthConfig, generate_take, seeds_for
from carapost.synth.expressions import CHANNELS

SMALL = dict(width=640, height=360)


@pytest.fixture(scope="module")
def take():
    # 40 frames: long enough for a blink (the first blink always falls inside short takes)
    return generate_take(SynthConfig(n_frames=40, seed=3, **SMALL))


def test_shapes(take):
    tr = take.truth
    F, M, C, B = 40, 80, 4, 18
    assert tr.xyz.shape == (F, M, 3) and tr.normals.shape == (F, M, 3)
    assert tr.xy.shape == tr.centroid_xy.shape == (F, M, C, 2)
    assert tr.visible.shape == tr.occluded.shape == tr.radius_px.shape == (F, M, C)
    assert tr.brim_xyz.shape == (B, 3) and tr.brim_xy.shape == (F, B, C, 2)
    assert tr.brim_visible.shape == (F, B, C)
    assert tr.R.shape == (F, C, 3, 3) and tr.t.shape == (F, C, 3)
    assert tr.expression.shape == (F, len(CHANNELS)) and tr.blink.shape == (F, 2)
    assert len(tr.names) == M == len(set(tr.names)) and len(tr.intrinsics) == C
    img = take.images(0)
    assert img.shape == (C, 360, 640) and img.dtype == np.uint8
    np.testing.assert_array_equal(take.image(0, 2), img[2])


def test_determinism():
    cfg = SynthConfig(n_frames=4, seed=11, **SMALL)
    a, b = generate_take(cfg), generate_take(cfg)
    for k, v in a.truth.arrays().items():
        np.testing.assert_array_equal(v, b.truth.arrays()[k], err_msg=k)
    np.testing.assert_array_equal(a.images(3), b.images(3))
    # images do not depend on the order they are asked for
    np.testing.assert_array_equal(a.image(1, 0), b.images(1)[0])
    c = generate_take(SynthConfig(n_frames=4, seed=12, **SMALL))
    assert not np.array_equal(a.truth.R, c.truth.R)
    assert not np.array_equal(a.images(0), c.images(0))


def test_truth_projections_are_consistent(take):
    tr = take.truth
    for c in range(4):
        xy = project(tr.xyz, tr.intrinsics[c], tr.R[:, c, None], tr.t[:, c, None])
        np.testing.assert_allclose(tr.xy[:, :, c], xy, atol=1e-6)
        bxy = project(tr.brim_xyz, tr.intrinsics[c], tr.R[:, c, None], tr.t[:, c, None])
        np.testing.assert_allclose(tr.brim_xy[:, :, c], bxy, atol=1e-6)
    vis = tr.visible
    assert np.all((tr.xy[vis] >= 0) & (tr.xy[vis] <= [639, 359]))
    assert np.all(tr.view_angle_deg[vis] <= 75.0)
    assert not np.any(vis & tr.occluded)
    assert not np.any(tr.partly_hidden & ~vis) and tr.partly_hidden.sum() < 0.05 * vis.sum()
    # the projected-disc centroid is within a few hundredths of a pixel of the projected centre
    d = np.linalg.norm(tr.centroid_xy - tr.xy, axis=-1)[vis]
    assert np.max(d) < 0.05 and np.median(d) < 0.02
    # dots are a few pixels across (2..10 px radius at 1280 x 720 -> 1..5 px here)
    r = tr.radius_px[vis]
    assert 1.0 < r.min() and r.max() < 5.0


def test_every_camera_sees_the_brim_and_most_of_the_face(take):
    tr = take.truth
    assert tr.brim_visible[0].all()
    n = tr.visible[0].sum(axis=0)
    assert np.all(n >= 0.6 * 80)
    for a, b in take.caddies:  # each caddy sees most of the face, both see the centre
        assert (tr.visible[0, :, a] & tr.visible[0, :, b]).sum() >= 40
    nose = tr.names.index("Nose_Tip")
    assert tr.visible[0, nose].all()


def test_poses_flex_and_slip(take):
    tr = take.truth
    C = camera_centre(tr.R, tr.t)
    C0 = camera_centre(tr.nominal_R, tr.nominal_t)
    d = np.linalg.norm(C - C0, axis=-1)
    assert 0.0 < d.max() < 1.0                                  # sub-mm flex
    rel = np.einsum("fcij,ckj->fcik", tr.R, tr.nominal_R)
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))
    assert 0.0 < ang.max() < 0.1                                # sub-0.1 degree
    np.testing.assert_allclose(np.einsum("fcij,fckj->fcik", tr.R, tr.R), np.broadcast_to(np.eye(3), tr.R.shape),
                               atol=1e-12)
    # helmet slip: the head drifts a little over the take, none at frame 0
    slip = np.linalg.norm(tr.head_t - tr.head_t[0], axis=1)
    assert slip[0] == 0.0 and 0.05 < slip[-1] < 5.0
    full = generate_take(SynthConfig(n_frames=200, expressions=False, blinks=False, **SMALL)).truth
    end = np.linalg.norm(full.head_t[-1] - full.head_t[0])
    assert 1.5 < end < 3.5  # slip_mm = 2 over the take


def test_marker_behind_the_nose_is_hidden(take):
    tr = take.truth
    # from the left cameras some right-side markers (beside the nose) are occluded, and
    # from the right cameras their mirror images
    left = [tr.names[m] for m in np.flatnonzero(tr.occluded[0, :, 0])]
    right = [tr.names[m] for m in np.flatnonzero(tr.occluded[0, :, 2])]
    assert left and all(name.split("_")[1] == "R" for name in left if "_" in name)
    assert sorted(n.replace("_R", "_L") for n in left) == sorted(right)
    m = tr.names.index(left[0])
    assert not tr.visible[0, m, 0] and tr.visible[0, m, 2]
    # the marker is facing the camera and inside the image: only the nose hides it
    assert tr.view_angle_deg[0, m, 0] < 75 and np.all(tr.xy[0, m, 0] > 0)
    # and no dot is drawn there: the image is skin-bright at its position
    img = take.render(0, [0], noise=False, blur_sigma=0)[0].astype(float)
    bg = take.render(0, [0], noise=False, blur_sigma=0, dots=False)[0].astype(float)
    x, y = np.round(tr.xy[0, m, 0]).astype(int)
    assert abs(img[y, x] - bg[y, x]) < 2
    # a visible marker, by contrast, is a dark dot
    v = tr.names.index("Nose_Tip")
    x, y = np.round(tr.xy[0, v, 0]).astype(int)
    assert img[y, x] < 0.3 * bg[y, x]


def test_blinks_hide_the_eyelid_markers(take):
    tr = take.truth
    lids = tr.eyelid_indices
    assert len(lids) == 2 and sorted(tr.names[i] for i in lids) == ["Lid_Upper_L", "Lid_Upper_R"]
    blink = np.flatnonzero(tr.blink_frames)
    assert 2 <= len(blink) <= 15            # hidden for a few frames
    assert not tr.visible[blink][:, lids].any()
    open_ = np.flatnonzero(tr.blink.max(axis=1) == 0)
    assert tr.visible[open_][:, lids].any(axis=(1, 2)).all()
    # the lid moves down as the eye closes (head frame)
    f = blink[len(blink) // 2]
    down = [(take.truth.head_R[k].T @ (tr.xyz[k, lids[0]] - tr.head_t[k]))[1] for k in (0, f)]
    assert down[1] < down[0] - 4.0
    # and is not drawn while hidden
    cam = int(np.argmax(tr.visible[0, lids[0]]))
    img = take.render(f, [cam], noise=False, blur_sigma=0)[0].astype(float)
    bg = take.render(f, [cam], noise=False, blur_sigma=0, dots=False)[0].astype(float)
    x, y = np.round(tr.xy[f, lids[0], cam]).astype(int)
    assert abs(img[y, x] - bg[y, x]) < 2


def test_dot_centroids_match_the_truth():
    """Intensity-weighted centroids of isolated dots in noise- and blur-free images."""
    st = generate_take(SynthConfig(n_frames=1, seed=5, vignetting=0.0, **SMALL))
    tr = st.truth
    img = st.render(0, noise=False, blur_sigma=0.0, as_float=True)
    bg = st.render(0, noise=False, blur_sigma=0.0, dots=False, as_float=True)
    scene = st.scene(0)
    errors = []
    for c in range(4):
        others = np.concatenate([tr.xy[0, :, c], tr.brim_xy[0, :, c]])
        for m in np.flatnonzero(tr.visible[0, :, c] & ~scene.dots_cut[:80, c]):
            x, y = tr.xy[0, m, c]
            r = tr.radius_px[0, m, c]
            d = np.linalg.norm(others - [x, y], axis=1)
            d[m] = np.inf
            R = int(np.ceil(r + 2))
            xi, yi = int(round(x)), int(round(y))
            if d.min() < 2 * R + r or tr.view_angle_deg[0, m, c] > 60:
                continue  # not isolated, or very oblique
            win = np.s_[yi - R:yi + R + 1, xi - R:xi + R + 1]
            b = bg[c][win]
            if b.std() > 0.08 * b.mean():
                continue  # on the brows or an eye: the weights would follow the albedo
            w = np.clip((b - img[c][win]) / b, 0, None)
            yy, xx = np.mgrid[yi - R:yi + R + 1, xi - R:xi + R + 1]
            errors.append(np.hypot((w * xx).sum() / w.sum() - x, (w * yy).sum() / w.sum() - y))
    errors = np.array(errors)
    assert len(errors) > 60
    assert errors.max() < 0.05 and np.median(errors) < 0.025


def test_image_looks_like_a_face_with_dark_dots(take):
    tr = take.truth
    img = take.render(0, noise=False).astype(float)
    for c in range(4):
        vis = np.flatnonzero(tr.visible[0, :, c])
        xy = np.round(tr.xy[0, vis, c]).astype(int)
        dots = img[c][xy[:, 1], xy[:, 0]]
        ring = img[c][xy[:, 1], np.clip(xy[:, 0] + 6, 0, 639)]
        assert np.median(dots) < 40 and np.median(ring) > 90      # dark dots on lit skin
        bxy = np.round(tr.brim_xy[0, :, c]).astype(int)
        card = img[c][bxy[:, 1] + 6, bxy[:, 0]]
        assert np.median(card) > 150                               # white card
        assert img[c][5:40, 5:40].mean() < 30                      # dark helmet behind
    noisy = take.images(0).astype(float)
    assert 0.5 < np.std(noisy - img) < 4.0                         # sensor noise


def test_white_markers_and_curved_brim():
    st = generate_take(SynthConfig(n_frames=2, marker_colour="white", curved_brim=True, brim="v1.1", **SMALL))
    tr = st.truth
    assert np.ptp(tr.brim_xyz[:, 2]) > 3.0 and len(tr.brim_xyz) == 14
    assert tr.brim_visible[0].all()
    img = st.render(0, [1], noise=False)[0].astype(float)
    vis = np.flatnonzero(tr.visible[0, :, 1])
    xy = np.round(tr.xy[0, vis, 1]).astype(int)
    dots = img[xy[:, 1], xy[:, 0]]
    ring = img[xy[:, 1], np.clip(xy[:, 0] + 6, 0, 639)]
    assert np.median(dots - ring) > 40


def test_expressions_move_the_face():
    st = generate_take(SynthConfig(n_frames=300, seed=1, blinks=False, slip_mm=0.0, flex=False, **SMALL))
    tr = st.truth
    jaw = tr.expression[:, CHANNELS.index("jaw")]
    assert jaw[0] == 0 and jaw.max() > 0.4
    chin = tr.names.index("Chin")
    head = np.einsum("fji,fj->fi", tr.head_R, tr.xyz[:, chin] - tr.head_t)
    f = int(np.argmax(jaw))
    assert head[f, 1] < head[0, 1] - 8 * jaw[f]   # the chin drops as the jaw opens
    brow = tr.names.index("Forehead_C")
    assert np.ptp(tr.xyz[:, brow], axis=0).max() < 0.5 + 7 * tr.expression[:, 5:7].max()


def test_high_motion_is_fast():
    tr_slow = generate_take(SynthConfig(n_frames=120, seed=2, **SMALL)).truth
    tr_fast = generate_take(SynthConfig(n_frames=120, seed=2, high_motion=True, **SMALL)).truth

    def speed(tr):
        v = np.linalg.norm(np.diff(tr.xy, axis=0), axis=-1)
        return np.nanpercentile(np.where(tr.visible[1:] & tr.visible[:-1], v, np.nan), 99)

    assert speed(tr_fast) > 2.0 * speed(tr_slow) and speed(tr_fast) > 1.5  # px / frame at 640 x 360


def test_seeds(take):
    s = seeds_for(take, frame=0)
    tr = take.truth
    assert s["frame"] == 0
    assert len(s["brim"]) >= 4
    for b in s["brim"]:
        assert set(b["xy"]) == {"0", "1", "2", "3"}
        for c, xy in b["xy"].items():
            np.testing.assert_allclose(xy, tr.brim_xy[0, b["brim_index"], int(c)], atol=1e-3)
    assert 5 <= len(s["face"]) <= 10 and len({f["name"] for f in s["face"]}) == len(s["face"])
    uv = []
    for f in s["face"]:
        m = tr.names.index(f["name"])
        cams = {int(c) for c in f["xy"]}
        assert any({a, b} <= cams for a, b in take.caddies)
        for c, xy in f["xy"].items():
            assert tr.visible[0, m, int(c)]
            np.testing.assert_allclose(xy, tr.xy[0, m, int(c)], atol=1e-3)
        uv.append(tr.marker_uv[m])
    uv = np.array(uv)
    assert np.ptp(uv[:, 0]) > 40 and np.ptp(uv[:, 1]) > 60   # spread across the face
    with pytest.raises(ValueError):
        seeds_for(take, frame=99)


def test_bad_arguments(take):
    with pytest.raises(ValueError, match="frame"):
        take.images(40)
    with pytest.raises(ValueError, match="camera"):
        take.image(0, 4)
    with pytest.raises(ValueError, match="n_markers"):
        generate_take(n_markers=12)


def test_partly_hidden_dots_are_cut_by_the_occluder(take):
    """Dots whose rim is partly behind the nose (or the card) lose the hidden part of their image."""
    from carapost.synth.dots import dot_patches

    r = take._renderer
    losses = []
    for f in (0, 10, 20, 30):
        scene = take.scene(f)
        for c in range(4):
            cut = np.flatnonzero(scene.dots_cut[:, c] & scene.dots_draw[:, c])
            if cut.size == 0:
                continue
            p = dot_patches(scene.dots_xyz[cut], scene.dots_normal[cut], scene.dots_radius[cut],
                            r.intrinsics[c], scene.R[c], scene.t[c])
            alpha = p.alpha.copy()
            r._cut(c, scene, p, np.arange(cut.size), alpha, scene.dots_radius[cut])
            assert np.all(alpha <= p.alpha)
            full = p.alpha.sum(axis=(1, 2))
            losses += list(1 - alpha.sum(axis=(1, 2))[full > 0] / full[full > 0])
    losses = np.array(losses)
    assert len(losses) > 0
    assert np.any((losses > 0.2) & (losses < 0.95))   # some dots are visibly cut, not removed
