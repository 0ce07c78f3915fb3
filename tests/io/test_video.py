"""Video files and image folders: frame-exact random access, verified counts, grayscale."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

av = pytest.importorskip("av")

from carapost.io.video import ImageFolderSource, VideoError, VideoSource, image_files, natural_key  # noqa: E402

REAL_VIDEOS = {"cam01.mp4": (1080, 1920), "cam02.mp4": (1080, 1920),
               "cam03.mp4": (1088, 1920), "cam04.mp4": (1088, 1920)}
W, H = 160, 128


def coded_frame(k: int) -> np.ndarray:
    """A textured frame carrying its index as an 8-bit barcode of 16x16 black/white blocks."""
    yy, xx = np.mgrid[0:H, 0:W]
    img = ((xx + yy) * 2 + 5 * k + 30 * np.sin(xx / 9.0 + k / 4.0)) % 200 + 20
    img = img.astype(np.uint8)
    for b in range(8):
        img[0:16, b * 20:b * 20 + 16] = 255 if (k >> b) & 1 else 0
    return img


def barcode(img: np.ndarray) -> int:
    return sum(int(img[4:12, b * 20 + 4:b * 20 + 12].mean() > 128) << b for b in range(8))


def write_video(path: Path, n: int, codec: str, options: dict | None = None, pix_fmt: str = "yuv420p",
                rotation_ccw: float | None = None) -> Path:
    with av.open(str(path), "w") as c:
        s = c.add_stream(codec, rate=30)
        s.width, s.height, s.pix_fmt = W, H, pix_fmt
        if options:
            s.options = options
        if rotation_ccw is not None:
            s.set_display_rotation(rotation_ccw)
        for k in range(n):
            for p in s.encode(av.VideoFrame.from_ndarray(coded_frame(k), format="gray")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def pyav_sequential(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as c:
        return [f.to_ndarray(format="gray") for f in c.decode(video=0)]


# -- real files --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def videos(real_data: Path) -> Path:
    d = real_data / "pose2sim-demo" / "videos"
    if not d.is_dir():
        pytest.skip("pose2sim demo videos not present")
    return d


@pytest.mark.parametrize("name", sorted(REAL_VIDEOS))
def test_real_mp4_frame_counts_are_verified(videos: Path, name: str) -> None:
    with VideoSource(videos / name) as v:
        assert (v.n_frames, (v.width, v.height), v.frame_rate, v.kind) == (100, REAL_VIDEOS[name], 60.0, "video")
        assert v.meta.camera_name == name[:-4] and v.warnings == [] and len(v._idx.pts) == 100


def check_random_access(path: Path, n_random: int) -> None:
    rng = np.random.default_rng(sum(map(ord, path.name)))
    sample = [int(i) for i in rng.choice(100, n_random, replace=False)] + [99, 61, 0]
    rng.shuffle(sample)
    sample += [40, 41, 42]                                    # forward steps continue decoding
    seq = {}
    with av.open(str(path)) as c:                            # independent sequential decode
        for i, f in enumerate(c.decode(video=0)):
            if i in sample:
                seq[i] = f.to_ndarray(format="gray")
    assert len(seq) == len(set(sample))
    with VideoSource(path) as v:
        for i in sample:
            img = v.read(i)
            assert img.dtype == np.uint8 and img.shape == (v.height, v.width)
            np.testing.assert_array_equal(img, seq[i], err_msg=f"{path.name} frame {i}")
        with pytest.raises(IndexError):
            v.read(100)


@pytest.mark.parametrize("name", ["cam02.mp4", "cam03.mp4"])    # VP9 (2 GOPs); H.264 with B-frames
def test_real_mp4_random_access_equals_sequential(videos: Path, name: str) -> None:
    check_random_access(videos / name, n_random=2)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(REAL_VIDEOS))
def test_real_mp4_random_access_equals_sequential_thorough(videos: Path, name: str) -> None:
    check_random_access(videos / name, n_random=12)


def test_real_vp9_frames_match_opencv_sequential_decode(videos: Path) -> None:
    """Independent decoder: frame i is OpenCV's sequential frame i (not i-1 or i+1)."""
    path = videos / "cam02.mp4"                               # VP9, keyframes at 0 and 60
    checks = (62, 5, 60)
    keep = {j for i in checks for j in (i - 1, i, i + 1)}
    cap = cv2.VideoCapture(str(path))
    ref = {}
    for j in range(max(keep) + 1):
        ok, img = cap.read()
        assert ok
        if j in keep:
            ref[j] = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
    cap.release()
    with VideoSource(path) as v:
        for i in checks:
            img = v.read(i)
            d = {j: float(np.abs(img - ref[j]).mean()) for j in (i - 1, i, i + 1)}
            assert d[i] < 0.2 and d[i] == min(d.values()), d


# -- synthetic videos ----------------------------------------------------------------------------
CASES = {
    "mp4-h264-bframes": ("mp4", "libx264", {"x264-params": "keyint=10:min-keyint=10:bframes=3:scenecut=0"}),
    "mp4-h264-open-gop": ("mp4", "libx264", {"x264-params": "keyint=12:min-keyint=12:open-gop=1:bframes=3:scenecut=0"}),
    "mov-mpeg4-bframes": ("mov", "mpeg4", {"g": "8", "bf": "2", "b": "4M"}),
    "mkv-h264": ("mkv", "libx264", {"x264-params": "keyint=15:bframes=2"}),
    "avi-mjpeg": ("avi", "mjpeg", None),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_synthetic_video_random_access(tmp_path: Path, case: str) -> None:
    ext, codec, opts = CASES[case]
    pix = "yuvj420p" if codec == "mjpeg" else "yuv420p"
    path = write_video(tmp_path / f"clip.{ext}", 40, codec, opts, pix)
    with VideoSource(path) as v:
        assert v.n_frames == 40 and (v.width, v.height) == (W, H)
        seq = [v.read(i) for i in range(40)]
    assert [barcode(f) for f in seq] == list(range(40))       # display order, nothing dropped
    for f, k in zip(seq, range(40)):
        assert np.abs(f.astype(float) - coded_frame(k)).mean() < 6.0
    order = np.random.default_rng(5).permutation(np.r_[np.arange(40), np.arange(40)])
    with VideoSource(path) as v:                              # a fresh decoder
        for i in order:
            np.testing.assert_array_equal(v.read(int(i)), seq[i], err_msg=f"{case} frame {i}")


def test_lossless_mkv_is_pixel_exact(tmp_path: Path) -> None:
    path = write_video(tmp_path / "lossless.mkv", 12, "ffv1", pix_fmt="gray")
    with VideoSource(path) as v:
        for i in (11, 3, 7, 0, 1):
            np.testing.assert_array_equal(v.read(i), coded_frame(i))


def test_display_rotation_is_read_into_metadata(tmp_path: Path) -> None:
    path = write_video(tmp_path / "phone.mp4", 3, "libx264", rotation_ccw=90)
    with VideoSource(path) as v:
        assert v.meta.rotation == 270                         # 90 deg anticlockwise = 270 clockwise
        assert (v.width, v.height) == (W, H)                  # pixels are never rotated


def test_frame_count_comes_from_decoding_not_the_header(tmp_path: Path) -> None:
    path = tmp_path / "cut.avi"
    vw = cv2.VideoWriter(str(path), cv2.CAP_OPENCV_MJPEG, cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (W, H), True)
    for k in range(30):
        vw.write(cv2.cvtColor(coded_frame(k), cv2.COLOR_GRAY2BGR))
    vw.release()
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.6)])            # the AVI header still claims 30
    with av.open(str(path)) as c:
        claimed = c.streams.video[0].frames
    with VideoSource(path) as v:
        assert claimed == 30 and 10 < v.n_frames < 30
        last = v.read(v.n_frames - 1)
        assert barcode(last) == v.n_frames - 1
        assert barcode(v.read(3)) == 3


def test_not_a_video(tmp_path: Path) -> None:
    p = tmp_path / "fake.mp4"
    p.write_text("definitely not a video")
    with pytest.raises(VideoError, match=r"fake\.mp4"):
        VideoSource(p)
    with pytest.raises(VideoError, match="no such video file"):
        VideoSource(tmp_path / "missing.mp4")


# -- image folders --------------------------------------------------------------------------------
def test_natural_sort() -> None:
    names = ["img_10.png", "img_9.png", "IMG_1.png", "img_100.png", "img_2.png"]
    assert sorted(names, key=natural_key) == ["IMG_1.png", "img_2.png", "img_9.png", "img_10.png", "img_100.png"]


def test_image_folder_order_and_grayscale(tmp_path: Path) -> None:
    exts = [".png", ".bmp", ".tif", ".png", ".png", ".png", ".bmp", ".tiff", ".png", ".png", ".png", ".jpg"]
    for k, ext in enumerate(exts):
        img = coded_frame(k)
        if k == 4:                                             # a colour image
            img = cv2.merge([img, (img // 2).astype(np.uint8), img])
        cv2.imwrite(str(tmp_path / f"frame_{k}{ext}"), img)
    (tmp_path / "notes.txt").write_text("not an image")
    src = ImageFolderSource(tmp_path, frame_rate=25.0)
    assert (src.n_frames, src.width, src.height, src.frame_rate, src.kind) == (12, W, H, 25.0, "images")
    assert [p.name for p in image_files(tmp_path)][9:12] == ["frame_9.png", "frame_10.png", "frame_11.jpg"]
    for k in range(11):
        got = src.read(k)
        if k == 4:
            colour = cv2.imread(str(tmp_path / "frame_4.png"), cv2.IMREAD_COLOR)
            want = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)      # libpng's own conversion: +-1
            assert np.abs(got.astype(int) - want).max() <= 1
        else:
            np.testing.assert_array_equal(got, coded_frame(k))
    assert barcode(src.read(11)) == 11                         # the JPEG one
    with pytest.raises(IndexError):
        src.read(12)


def test_image_folder_errors(tmp_path: Path) -> None:
    with pytest.raises(VideoError, match="no png/jpg"):
        ImageFolderSource(tmp_path)
    cv2.imwrite(str(tmp_path / "a_1.png"), coded_frame(1))
    cv2.imwrite(str(tmp_path / "a_2.png"), coded_frame(2)[:64])
    (tmp_path / "a_3.png").write_bytes(b"\x89PNG broken")
    src = ImageFolderSource(tmp_path)
    with pytest.raises(VideoError, match=r"a_2\.png: image is 160x64"):
        src.read(1)
    with pytest.raises(VideoError, match=r"a_3\.png: not a readable image"):
        src.read(2)
    with pytest.raises(VideoError, match="not a folder"):
        ImageFolderSource(tmp_path / "a_1.png")


def test_packet_index_matches_decoded_index(tmp_path: Path, videos: Path) -> None:
    """verify=False (demux only, for long videos) finds the same frames on intact files."""
    from carapost.io import video as video_mod

    clip = write_video(tmp_path / "b.mp4", 30, "libx264", CASES["mp4-h264-open-gop"][2])
    for path in (clip, videos / "cam02.mp4", videos / "cam03.mp4"):
        video_mod._INDEX_CACHE.clear()
        with VideoSource(path, verify=False) as fast:
            assert not fast._idx.verified
            fast_pts, first = fast._idx.pts, fast.read(1)
        with VideoSource(path) as full:
            assert full._idx.verified and full._idx.pts == fast_pts and full.n_frames == len(fast_pts)
            np.testing.assert_array_equal(full.read(1), first)
        with VideoSource(path, verify=False) as again:        # a verified index serves both
            assert again._idx.verified
