import pytest

from carapost.model.params import (
    BlobParameters,
    Parameters,
    TrackingParameters,
    dense_156_preset,
    restore_defaults,
    sparse_35_preset,
)


def test_guide_defaults():
    p = Parameters()
    assert p.tracking.patch_match_threshold == 0.8
    assert p.tracking.face_point_tracking_distance == 35
    assert p.tracking.face_point_max_elastic_prediction_distance == 15
    assert p.tracking.brim_point_tracking_distance == 15
    assert p.tracking.patch_match_size == 15
    assert p.tracking.max_allowed_2d_projection_error == 5
    assert p.tracking.max_allowed_3d_point_error == 5
    assert p.tracking.single_sensor_tracking_threshold == 0.5
    assert p.tracking.blob_size_difference_threshold == 0.75
    assert (p.blobs.black_min_radius, p.blobs.black_max_radius, p.blobs.black_threshold) == (4, 50, 0.4)
    assert p.blobs.find_black_blobs and not p.blobs.find_white_blobs
    assert (p.init3d.max_allowed_depth, p.init3d.max_3d_distance_to_merge,
            p.init3d.max_allowed_symmetric_epipolar_distance) == (35, 5, 5)
    assert (p.init3d.auto_min_views, p.init3d.auto_max_reprojection_error) == (3, 2.0)   # not the guide's
    assert (p.rom.rom_face_point_tracking_distance, p.rom.rom_brim_point_tracking_distance) == (50, 30)
    assert p.stabilization.stable_points_percent == 0.25 and p.stabilization.max_processing_iterations == 50
    assert p.tracker.break_threshold == 0.9
    assert p.display.font_size == 10


def test_validation_rejects_out_of_range_with_message():
    with pytest.raises(ValueError, match=r"Blob Parameters: Black Threshold must be in the range 0 to 1"):
        BlobParameters(black_threshold=1.5)
    t = TrackingParameters()
    with pytest.raises(ValueError, match="Patch Match Size must be a whole number"):
        t.set("Patch Match Size", 7.5)
    assert t.patch_match_size == 15  # unchanged after a rejected set
    with pytest.raises(ValueError, match="Min Radius"):
        BlobParameters(white_min_radius=20, white_max_radius=10)
    with pytest.raises(ValueError, match="True or False"):
        t.set("remove_bad_3d_points", 3.2)


def test_get_set_by_guide_names():
    p = Parameters()
    p.set("Tracking Parameters", "Face Point Tracking Distance", 40)
    assert p.get("tracking", "face_point_tracking_distance") == 40.0
    with pytest.raises(KeyError, match="no property named"):
        p.get("tracking", "nonsense")
    with pytest.raises(KeyError, match="no property group"):
        p.section("nope")


def test_presets_and_restore():
    dense = dense_156_preset()
    assert dense.init3d.max_allowed_depth == 16
    assert dense.tracking == TrackingParameters()
    sparse = sparse_35_preset()
    assert sparse.init3d.max_allowed_depth == 60
    assert sparse.tracking.face_point_max_elastic_prediction_distance == 25
    assert sparse.tracking.max_allowed_3d_point_error == 10
    assert sparse.tracking.allow_single_sensor_tracking is False
    restore_defaults(sparse)
    assert sparse == Parameters()


def test_dict_roundtrip_ignores_unknown():
    p = sparse_35_preset()
    d = p.to_dict()
    d["tracking"]["from_the_future"] = 1
    assert Parameters.from_dict(d) == p
