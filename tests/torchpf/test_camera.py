"""Camera model: projection against cv2.projectPoints, rigs, cameras.yaml and OpenCV FileStorage files."""

import math
import os

import cv2
import numpy as np
import pytest
import torch

from torchpf.camera import (
    Camera,
    CameraFileError,
    CameraRig,
    camera_ring,
    load_cameras,
    look_at,
    project_points,
    save_cameras,
)


def random_camera(rng: np.random.Generator, dist: bool = True) -> Camera:
    rvec = rng.normal(size=3) * 0.5
    R = cv2.Rodrigues(rvec)[0]
    t = rng.normal(size=3) * 0.2 + np.array([0, 0, 4.0])
    f = rng.uniform(300, 900)
    K = np.array(
        [[f, 0, rng.uniform(300, 340)], [0, f * rng.uniform(0.95, 1.05), rng.uniform(220, 260)], [0, 0, 1]]
    )
    d = np.array([0.1, -0.05, 0.001, -0.002, 0.01]) * rng.uniform(0.5, 1.5, 5) if dist else None
    return Camera(K, R, t, d, width=640, height=480, name="c")


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("dist", [True, False])
def test_project_matches_opencv(seed, dist):
    rng = np.random.default_rng(seed)
    cam = random_camera(rng, dist)
    X = rng.normal(size=(200, 3)) * 0.8
    ref, _ = cv2.projectPoints(
        X,
        cv2.Rodrigues(cam.R.numpy())[0],
        cam.t.numpy(),
        cam.K.numpy(),
        None if cam.dist is None else cam.dist.numpy(),
    )
    uv64 = cam.project(torch.from_numpy(X))
    assert uv64.dtype == torch.float64
    np.testing.assert_allclose(uv64.numpy(), ref[:, 0], atol=1e-8)
    uv32 = cam.project(torch.from_numpy(X).float())
    assert uv32.dtype == torch.float32
    np.testing.assert_allclose(uv32.numpy(), ref[:, 0], atol=2e-3)
    # the depth from the same transform is R x + t's third coordinate
    uv, depth = cam.project(torch.from_numpy(X), return_depth=True)
    assert torch.equal(uv, uv64)
    np.testing.assert_allclose(depth.numpy(), (X @ cam.R.numpy().T + cam.t.numpy())[:, 2], atol=1e-12)


def test_project_batched_shapes_and_gradient():
    cam = random_camera(np.random.default_rng(1))
    X = torch.randn(4, 5, 7, 3, dtype=torch.float64) * 0.5
    uv = cam.project(X)
    assert uv.shape == (4, 5, 7, 2)
    np.testing.assert_allclose(uv[2, 3].numpy(), cam.project(X[2, 3]).numpy())
    Xg = X[0, 0].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda p: cam.project(p), (Xg,))
    # The functional form with every parameter differentiable (calibration by gradient descent).
    K = cam.K.clone().requires_grad_()
    d = cam.dist.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda K, d: project_points(X[0, 0], K, cam.R, cam.t, d), (K, d))


def test_undistorted_projection_is_the_formula():
    """Without distortion the projection is one matrix product with K R folded (and the entries of K the
    formula does not read ignored): the same pixels and gradients as the step-by-step formula."""
    from torchpf.camera import _camera_to_pixels

    cam = random_camera(np.random.default_rng(2), dist=False)
    X = torch.randn(3, 6, 3, dtype=torch.float64) * 0.5
    K = cam.K.clone()
    K[1, 0], K[2] = 7.0, torch.tensor([0.1, 0.2, 3.0], dtype=torch.float64)  # not read by the formula
    ref = _camera_to_pixels(X @ cam.R.T + cam.t, K, None)
    torch.testing.assert_close(project_points(X, K, cam.R, cam.t), ref, rtol=0, atol=1e-9)
    args = [t.clone().requires_grad_() for t in (X[0], cam.K, cam.R, cam.t)]
    assert torch.autograd.gradcheck(lambda *a: project_points(*a), args)
    other = random_camera(np.random.default_rng(3), dist=False)
    other.name = "d"
    rig = CameraRig([cam, other])
    torch.testing.assert_close(
        rig.to_camera(X), torch.stack([c.to_camera(X) for c in (cam, other)], -2), rtol=0, atol=1e-12
    )


def test_depth_in_front_and_center():
    cam = look_at((0.0, -4.0, 1.5), (0.0, 0.0, 1.0), width=160, height=120)
    np.testing.assert_allclose(cam.center.numpy(), [0.0, -4.0, 1.5], atol=1e-12)
    pts = torch.tensor([[0.0, 0.0, 1.0], [0.0, -8.0, 1.0]], dtype=torch.float64)
    assert cam.in_front(pts).tolist() == [True, False]
    assert cam.depth(pts)[0] == pytest.approx(math.hypot(4.0, 0.5), rel=1e-12)
    assert cam.in_image(pts).tolist() == [True, False]


def test_look_at_conventions():
    cam = look_at((3.0, 1.0, 2.0), (0.0, 0.0, 1.0), width=200, height=100, fov_deg=60)
    uv = cam.project(torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.5]], dtype=torch.float64))
    # The target lands on the principal point; a point above it (world z up) lands higher (smaller v).
    np.testing.assert_allclose(uv[0].numpy(), [99.5, 49.5], atol=1e-9)
    assert uv[1, 1] < uv[0, 1]
    assert abs(uv[1, 0] - uv[0, 0]) < 1e-9
    R = cam.R.numpy()
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert cam.K[0, 0].item() == pytest.approx(100 / math.tan(math.radians(30)))


def test_camera_ring():
    rig = camera_ring(3, radius=4.0, height=1.5, target=(0.5, 0.0, 1.0), width=160, height_px=120)
    assert list(rig) == ["cam0", "cam1", "cam2"]
    centres = torch.stack([c.center for c in rig.values()])
    d = (centres[:, :2] - torch.tensor([0.5, 0.0], dtype=torch.float64)).norm(dim=-1)
    np.testing.assert_allclose(d.numpy(), 4.0, atol=1e-12)
    np.testing.assert_allclose(centres[:, 2].numpy(), 1.5, atol=1e-12)
    angles = torch.atan2(centres[:, 1], centres[:, 0] - 0.5)
    gaps = torch.diff(torch.sort(angles).values)
    np.testing.assert_allclose(gaps.numpy(), 2 * math.pi / 3, atol=1e-9)
    for c in rig.values():
        np.testing.assert_allclose(
            c.project(torch.tensor([0.5, 0.0, 1.0], dtype=torch.float64)).numpy(), [79.5, 59.5]
        )


def test_pixel_rays_reproject_to_pixel_centres():
    cam = random_camera(np.random.default_rng(3))
    rays = cam.pixel_rays(48, 64, stride=1)  # a 64x48 grid over the 640x480 image
    pts = cam.center + 3.0 * rays
    uv = cam.project(pts)
    jj, ii = np.meshgrid(np.arange(64), np.arange(48))
    np.testing.assert_allclose(uv[..., 0].numpy(), (jj + 0.5) * 10 - 0.5, atol=1e-3)
    np.testing.assert_allclose(uv[..., 1].numpy(), (ii + 0.5) * 10 - 0.5, atol=1e-3)
    np.testing.assert_allclose(rays.norm(dim=-1).numpy(), 1.0, atol=1e-12)


def test_resized_is_consistent():
    cam = random_camera(np.random.default_rng(4), dist=False)
    small = cam.resized(160, 120)
    X = torch.randn(20, 3, dtype=torch.float64) * 0.5
    np.testing.assert_allclose(
        small.project(X).numpy(), ((cam.project(X) + 0.5) * 0.25 - 0.5).numpy(), atol=1e-9
    )


def _mixed_rig():
    rng = np.random.default_rng(8)
    cams = [random_camera(rng), random_camera(rng, dist=False), random_camera(rng)]
    for i, c in enumerate(cams):
        c.name = f"c{i}"
    cams[2] = cams[2].resized(320, 240)  # cameras of different sizes
    return cams, CameraRig(cams, depth_camera="c1")


def test_rig_projects_into_every_camera_at_once():
    cams, rig = _mixed_rig()
    X = torch.randn(4, 6, 3, dtype=torch.float64) * 0.5
    uv = rig.project(X)
    assert uv.shape == (4, 6, 3, 2)
    for v, cam in enumerate(cams):
        torch.testing.assert_close(uv[..., v, :], cam.project(X), rtol=0, atol=1e-9)
        torch.testing.assert_close(rig.depth(X)[..., v], cam.depth(X), rtol=0, atol=1e-12)
        assert rig.focal()[v].item() == pytest.approx(cam.focal)
    assert rig.in_front(X).shape == (4, 6, 3)
    small = rig.resized(160, 120)
    assert small.sizes == [(160, 120)] * 3 and rig.resized(640, 480) is not rig
    for v, cam in enumerate(cams):
        torch.testing.assert_close(
            small.project(X)[..., v, :], cam.resized(160, 120).project(X), rtol=0, atol=1e-9
        )
    same = CameraRig(cams[:2])
    assert same.resized(640, 480) is same


def test_rig_is_a_module_and_a_mapping():
    cams, rig = _mixed_rig()
    assert list(rig) == ["c0", "c1", "c2"] and len(rig) == 3 and "c1" in rig and rig.depth_camera == "c1"
    assert rig["c1"].dist is None and rig[0].name == "c0" and rig.index("c2") == 2
    torch.testing.assert_close(rig["c2"].K, cams[2].K)
    assert (rig["c2"].width, rig["c2"].height) == (320, 240)
    assert [c.name for c in rig.values()] == ["c0", "c1", "c2"] and dict(rig).keys() == {"c0", "c1", "c2"}
    with pytest.raises(KeyError):
        rig["nope"]
    with pytest.raises(ValueError, match="duplicate"):
        CameraRig([cams[0], cams[0]])
    holder = torch.nn.Module()
    holder.rig = rig
    holder.to(torch.float32)
    assert rig.K.dtype == torch.float32 and "rig.K" in dict(holder.named_buffers())
    assert rig.project(torch.zeros(2, 3)).dtype == torch.float32
    copy = CameraRig(rig)  # a copy with its own buffers
    assert copy.K.data_ptr() != rig.K.data_ptr() and list(copy) == list(rig)


def test_cameras_yaml_roundtrip(tmp_path):
    rng = np.random.default_rng(5)
    cams = [random_camera(rng), random_camera(rng, dist=False)]
    cams[0].name, cams[1].name = "left", "kinect"
    path = tmp_path / "seq" / "cameras.yaml"
    save_cameras(path, cams, depth_camera="kinect")
    assert sorted(os.listdir(path.parent)) == ["cameras.yaml"]  # no temp file left behind
    rig = load_cameras(path)
    assert list(rig) == ["left", "kinect"] and rig.depth_camera == "kinect"
    for a, b in zip(cams, rig.values(), strict=True):
        for k in ("K", "R", "t"):
            np.testing.assert_allclose(getattr(a, k).numpy(), getattr(b, k).numpy(), rtol=1e-15)
        assert (a.width, a.height) == (b.width, b.height)
        X = torch.randn(10, 3, dtype=torch.float64)
        np.testing.assert_allclose(a.project(X).numpy(), b.project(X).numpy(), rtol=1e-12)
    assert rig["kinect"].dist is None


def _write_fs(path, data):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in data.items():
        fs.write(k, v)
    fs.release()


@pytest.mark.parametrize("ext", ["yml", "xml"])
def test_load_opencv_filestorage(tmp_path, ext):
    rng = np.random.default_rng(6)
    cam = random_camera(rng)
    rvec = cv2.Rodrigues(cam.R.numpy())[0]
    path = tmp_path / f"calib.{ext}"
    _write_fs(
        path,
        {
            "camera_matrix": cam.K.numpy(),
            "distortion_coefficients": cam.dist.numpy().reshape(1, 5),
            "image_width": 640,
            "image_height": 480,
            "rvec": rvec,
            "tvec": cam.t.numpy().reshape(3, 1),
        },
    )
    rig = load_cameras(path)
    (loaded,) = rig.values()
    assert loaded.name == "calib" and (loaded.width, loaded.height) == (640, 480)
    X = torch.randn(30, 3, dtype=torch.float64) * 0.5
    np.testing.assert_allclose(loaded.project(X).numpy(), cam.project(X).numpy(), atol=1e-9)


def test_load_opencv_multi_camera_map(tmp_path):
    path = tmp_path / "rig.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name in ("a", "b"):
        fs.startWriteStruct(name, cv2.FileNode_MAP)
        fs.write("cameraMatrix", np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]))
        fs.write("distCoeffs", np.zeros((1, 5)))
        fs.write("R", np.eye(3))
        fs.write("T", np.array([[0.0], [0.0], [3.0]]))
        fs.write("image_size", np.array([[640.0, 480.0]]))
        fs.endWriteStruct()
    fs.release()
    rig = load_cameras(path)
    assert list(rig) == ["a", "b"]
    assert rig["b"].width == 640 and rig["b"].height == 480
    np.testing.assert_allclose(rig["a"].t.numpy(), [0, 0, 3.0])


_I = "[[1,0,0],[0,1,0],[0,0,1]]"


def _entry(K=_I, R=_I, t="[0,0,0]", width="4"):
    lines = [f"    K: {K}" if K else "", f"    R: {R}", f"    t: {t}", f"    width: {width}", "    height: 3"]
    return "cameras:\n  c0:\n" + "\n".join(x for x in lines if x) + "\n"


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        (_entry(K=None), "'K'"),
        (_entry(K="[[1,0,0],[0,1,0]]"), "'K'"),
        (_entry(R="[[2,0,0],[0,1,0],[0,0,1]]"), "'R'"),
        (_entry(t="[0,0]"), "'t'"),
        (_entry(width="-4"), "'width'"),
        (_entry(width=".inf"), "'width'"),
        (_entry(width="1e400"), "'width'"),
        (_entry(width="100000000000000000000000"), "'width'"),
        (_entry(width=".nan"), "'width'"),
        (_entry(K="[[0,0,0],[0,0,0],[0,0,0]]"), "focal"),
        (_entry(K="[[-500,0,2],[0,500,1],[0,0,1]]"), "focal"),
        (_entry(K="[[500,0,2],[0,500,1],[0,0,2]]"), "'K'"),
        (_entry(K="[[500,0,2],[0,500,1],[1,0,1]]"), "'K'"),
        (_entry(K="[[500,0,2],[3,500,1],[0,0,1]]"), "'K'"),
        (_entry(K="[[.nan,0,2],[0,500,1],[0,0,1]]"), "'K'"),
        ("cams: {}\n", "'cameras'"),
        ("cameras: {c0: {K: 1}}\ndepth_camera: nope\n", "'K'"),
    ],
)
def test_bad_camera_files_name_file_and_key(tmp_path, text, needle):
    path = tmp_path / "cameras.yaml"
    path.write_text(text)
    with pytest.raises(CameraFileError) as e:
        load_cameras(path)
    assert str(path) in str(e.value) and needle in str(e.value)


@pytest.mark.parametrize("name", ["../../outside", "/abs", "a/b", ".hidden", "..", "-x", "", "a b", "x" * 65])
def test_camera_names_are_safe_identifiers(tmp_path, name):
    path = tmp_path / "cameras.yaml"
    path.write_text(_entry().replace("  c0:", f"  {name!r}:"))
    with pytest.raises(CameraFileError) as e:
        load_cameras(path)
    assert str(path) in str(e.value) and repr(name) in str(e.value)
    with pytest.raises(CameraFileError, match="safe identifier"):  # nor written anywhere
        save_cameras(tmp_path / "out.yaml", [look_at((0, -3, 1), name=name)])
    assert not (tmp_path / "out.yaml").exists()


def test_opencv_file_errors_name_the_file(tmp_path):
    path = tmp_path / "calib.yml"
    path.write_text("%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: [\n")
    with pytest.raises(CameraFileError, match="calib.yml"):
        load_cameras(path)
    path.write_text(
        "%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 100000\n   cols: 100000\n   dt: d\n"
        "   data: [1.0]\nimage_width: 4\nimage_height: 3\n"
    )
    with pytest.raises(CameraFileError, match=r"calib\.yml: line 3: an opencv-matrix needs rows and cols"):
        load_cameras(path)  # refused before allocating 10^10 numbers
    path.write_bytes(b"cameras:\n  c0: \xff\xfe\n")
    with pytest.raises(CameraFileError, match="calib.yml: not UTF-8"):
        load_cameras(path)


def test_bad_depth_camera_name(tmp_path):
    cam = look_at((0, -3, 1), name="c0")
    path = tmp_path / "cameras.yaml"
    save_cameras(path, [cam])
    text = path.read_text() + "depth_camera: nope\n"
    path.write_text(text)
    with pytest.raises(CameraFileError, match="depth_camera"):
        load_cameras(path)
    with pytest.raises(ValueError):
        CameraRig([cam], depth_camera="nope")


def test_project_follows_the_points_device_and_dtype(device, dtype):
    cam = random_camera(np.random.default_rng(7))
    X = torch.randn(100, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    out = cam.project(X.to(device, dtype))
    assert out.device.type == device.type and out.dtype == dtype
    tol = 1e-9 if dtype == torch.float64 else 1e-3
    np.testing.assert_allclose(out.cpu().double().numpy(), cam.project(X).numpy(), atol=tol, rtol=tol)
    rig = CameraRig([cam]).to(device)
    torch.testing.assert_close(rig.project(X.to(device, dtype))[..., 0, :], out)
    assert rig[0].pixel_rays(12, 16).shape == (12, 16, 3)  # OpenCV on host copies of device tensors


def test_learnable_rig_parameters(device):
    rig = camera_ring(3, width=160, height_px=120)
    fitted = CameraRig(rig, learnable=True).to(device)
    assert {n for n, _ in fitted.named_parameters()} == {"K", "rotation_update", "t", "dist"}
    x = torch.randn(7, 3, dtype=torch.float64, device=device)
    torch.testing.assert_close(fitted.project(x).cpu(), rig.project(x.cpu()))
    fitted.resized(80, 60).project(x).square().sum().backward()  # through the resized intrinsics too
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in fitted.parameters())
    with torch.no_grad():
        fitted.rotation_update[1] = torch.tensor([0.1, -0.2, 0.3])
    R = fitted.R  # the current rotation, exp([w]x) R_0: still a rotation
    eye = torch.eye(3, dtype=R.dtype, device=device).expand(3, 3, 3)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye)
    torch.testing.assert_close(fitted[1].R, R[1])
    assert not torch.allclose(R[1].cpu(), rig.R[1]) and torch.equal(R[0].cpu(), rig.R[0])
    with pytest.raises(ValueError, match="learnable"):
        CameraRig(rig, learnable=["f"])


def test_yaml_numbers_are_plain_decimals(tmp_path):
    """YAML 1.1 reads 1_000 as 1000 and 0x1f as 31: cameras.yaml and tracker configs take plain numbers."""
    from torchpf.io import load_yaml

    assert load_yaml("a: 1_000\nb: 0x1f\nc: 1:30\nd: 1e-3\ne: -2.5\nf: 12") == {
        "a": "1_000",
        "b": "0x1f",
        "c": "1:30",
        "d": 1e-3,
        "e": -2.5,
        "f": 12,
    }
    cam = random_camera(np.random.default_rng(1))
    cam.name = "c0"
    path = tmp_path / "cameras.yaml"
    save_cameras(path, [cam])
    text = path.read_text()
    path.write_text(text.replace(f"width: {cam.width}", "width: 1_000", 1))
    with pytest.raises(ValueError, match="cameras.yaml.*width"):
        load_cameras(path)
