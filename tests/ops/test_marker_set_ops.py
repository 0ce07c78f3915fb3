import numpy as np

from carapost.model.take import Take
from carapost.ops.marker_set import find_swaps, label_from_template, repair_swaps, save_template
from carapost.ops.session import Session


def marker_take(synth, frames=40):
    tr = synth.truth
    take = Take.new([], frames, 60.0)
    M = len(tr.names)
    take.add_points(M)
    take.xyz[:] = tr.xyz[:frames]
    take.recon[:] = 3
    return take, tr


def test_template_roundtrip_labels_a_new_take(tiny_synth, tmp_path, undo_check):
    take, tr = marker_take(tiny_synth, frames=6)
    s = Session(take)
    for c in range(take.n_points):
        take.points.labels[c] = tr.names[c]
    take.sticks = np.array([[0, 1], [1, 2]])
    take.stick_colours = np.zeros((2, 3), np.uint8)
    save_template(take, 0, tmp_path / "set.json")
    # a second take: same markers, shuffled, unlabelled, another frame
    other, _ = marker_take(tiny_synth, frames=6)
    perm = np.random.default_rng(1).permutation(other.n_points)
    other.xyz[:] = other.xyz[:, perm]
    s2 = Session(other)
    change, fit = label_from_template(other, 5, tmp_path / "set.json")
    undo_check(s2, change)
    names = s2.take.points.labels
    assert sum(names[j] == tr.names[perm[j]] for j in range(len(perm))) >= len(perm) - 1
    assert len(s2.take.sticks) == 2


def test_find_and_repair_swap(undo_check):
    from carapost.synth.mocap import face_motion

    motion = face_motion(n_markers=35, n_frames=240, seed=3)
    take = Take.new([], motion.xyz.shape[0], 60.0)
    take.add_points(motion.xyz.shape[1])
    take.xyz[:] = motion.xyz
    good = take.xyz.copy()
    a, b = 3, 9
    take.xyz[120:, [a, b]] = take.xyz[120:, [b, a]]
    s = Session(take)
    rep = find_swaps(take)
    assert rep.relabels, "the swap is found"
    undo_check(s, repair_swaps(take, rep.relabels))
    np.testing.assert_allclose(s.take.xyz, good)
