"""GSMSDRModel in-process: camera maths, seed handling, offline LPIPS, NaN guard, checkpoint loading."""

from __future__ import annotations

import io
import math
import warnings

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.models.splatfacto import SH2RGB

from gsmsdr_ns.plugin.cameras import intrinsics_at_scale, viewmats_from_camera_to_worlds
from gsmsdr_ns.plugin.checkpoint_io import checkpoint_safe_globals
from gsmsdr_ns.plugin.finite_check import NonFiniteLossError
from gsmsdr_ns.plugin.lpips import LPIPSUnavailable, lpips_backbone_cache_path
from gsmsdr_ns.plugin.model import GSMSDRModelConfig, GSMSDRWarning

W, H = 32, 24


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def look_from(position, target=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """[3, 4] nerfstudio (OpenGL) camera-to-world looking from ``position`` at ``target``."""
    position, target = np.asarray(position, float), np.asarray(target, float)
    back = position - target
    back /= np.linalg.norm(back)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    return torch.tensor(np.stack([right, up, back, position], axis=1), dtype=torch.float32)


def make_camera(c2w: torch.Tensor, width: int = W, height: int = H) -> Cameras:
    return Cameras(
        camera_to_worlds=c2w[None],
        fx=torch.tensor([[30.0]]),
        fy=torch.tensor([[30.0]]),
        cx=torch.tensor([[width / 2]]),
        cy=torch.tensor([[height / 2]]),
        width=torch.tensor([[width]]),
        height=torch.tensor([[height]]),
        camera_type=CameraType.PERSPECTIVE,
    )


def seed_cloud(n: int = 64, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    xyz = torch.rand(n, 3, generator=gen) - 0.5
    rgb = torch.randint(0, 256, (n, 3), generator=gen, dtype=torch.uint8)
    return xyz, rgb


def make_model(seed_points=None, **config):
    config = GSMSDRModelConfig(**{"num_random": 100, **config})
    scene_box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GSMSDRWarning)
        return config.setup(scene_box=scene_box, num_train_data=4, seed_points=seed_points)


# -- camera helpers ----------------------------------------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_viewmat_inverts_the_pose_with_opencv_axes(seed):
    rng = np.random.default_rng(seed)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.from_numpy(random_rotation(rng))
    c2w[:3, 3] = torch.from_numpy(rng.normal(size=3) * 3)
    viewmat = viewmats_from_camera_to_worlds(c2w[None, :3, :])[0]
    # world->camera after camera->world leaves only the OpenGL->OpenCV axis flip
    torch.testing.assert_close(viewmat @ c2w, torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64)))
    # a point one unit along the camera's viewing direction (OpenGL -z) lands at OpenCV z = +1
    ahead = c2w @ torch.tensor([0.0, 0.0, -1.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(viewmat @ ahead, torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=torch.float64))


def test_viewmat_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\[C, 3, 4\]"):
        viewmats_from_camera_to_worlds(torch.eye(4))


@pytest.mark.parametrize("downscale", [1, 2, 4])
def test_intrinsics_match_nerfstudio_rescaling_without_mutating(downscale):
    camera = make_camera(look_from([2.0, 0.0, 1.0]), width=37, height=23)
    K, width, height = intrinsics_at_scale(camera, downscale, torch.device("cpu"))
    assert camera.width.item() == 37  # untouched
    reference = make_camera(look_from([2.0, 0.0, 1.0]), width=37, height=23)
    reference.rescale_output_resolution(1 / downscale)
    torch.testing.assert_close(K, reference.get_intrinsics_matrices().reshape(1, 3, 3))
    assert (width, height) == (reference.width.item(), reference.height.item())


def test_intrinsics_are_built_on_the_cameras_device_without_a_host_copy():
    """On a GPU the camera of a training step lives on the device; its intrinsics must not round-trip through the
    host (nerfstudio's get_intrinsics_matrices fills a CPU matrix). The meta device has no data to copy, so any
    host round trip fails here."""
    camera = make_camera(look_from([2.0, 0.0, 1.0]), width=37, height=23).to("meta")
    K, width, height = intrinsics_at_scale(camera, 2, torch.device("meta"), full_size=(37, 23))
    assert K.device.type == "meta" and K.shape == (1, 3, 3) and (width, height) == (18, 11)


# -- construction ------------------------------------------------------------------------------------------------


def test_seed_colours_initialise_the_base_colour_on_cpu():
    xyz, rgb = seed_cloud()
    model = make_model(seed_points=(xyz, rgb))
    assert model.num_points == xyz.shape[0]
    torch.testing.assert_close(model.means.data, xyz)
    torch.testing.assert_close(SH2RGB(model.features_dc.data), rgb.float() / 255, atol=1e-5, rtol=0)
    assert torch.count_nonzero(model.features_rest) == 0


def test_seed_colours_with_sh_degree_zero_use_logits():
    xyz, rgb = seed_cloud()
    model = make_model(seed_points=(xyz, rgb), sh_degree=0)
    torch.testing.assert_close(model.colors.data, (rgb.float() / 255).clamp(1e-6, 1 - 1e-6), atol=1e-4, rtol=0)


@pytest.mark.parametrize("num_points", [0, 3])
def test_too_few_seed_points_fall_back_to_random_init_with_warning(num_points):
    xyz, rgb = seed_cloud(num_points)
    config = GSMSDRModelConfig(num_random=123)
    scene_box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with pytest.warns(GSMSDRWarning, match=rf"{num_points} usable points.*123 random Gaussians"):
        model = config.setup(scene_box=scene_box, num_train_data=4, seed_points=(xyz, rgb))
    assert model.num_points == 123


def test_non_finite_seed_points_are_dropped():
    xyz, rgb = seed_cloud(10)
    xyz[3] = float("nan")
    model = make_model(seed_points=(xyz, rgb))
    assert model.num_points == 9
    assert torch.isfinite(model.means).all()


def test_lpips_is_left_out_offline_with_one_warning(tmp_path, monkeypatch):
    import torchmetrics.image.lpip as lpip_module

    import gsmsdr_ns.plugin.lpips as lpips_module

    monkeypatch.setattr(lpips_module, "_warning_shown", False)  # earlier tests in this process saw it
    original_class = lpip_module.LearnedPerceptualImagePatchSimilarity
    monkeypatch.setattr(torch.hub, "_hub_dir", str(tmp_path / "hub"))  # an empty torch hub cache
    assert lpips_backbone_cache_path().parent == tmp_path / "hub" / "checkpoints"
    config = GSMSDRModelConfig()
    scene_box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = config.setup(scene_box=scene_box, num_train_data=4, seed_points=seed_cloud())
    lpips_warnings = [w for w in caught if issubclass(w.category, GSMSDRWarning) and "LPIPS" in str(w.message)]
    assert len(lpips_warnings) == 1, [str(w.message) for w in caught]
    assert str(tmp_path / "hub" / "checkpoints") in str(lpips_warnings[0].message)
    assert not model.has_lpips and isinstance(model.lpips, LPIPSUnavailable)
    assert lpip_module.LearnedPerceptualImagePatchSimilarity is original_class  # the swap was undone
    assert not any(key.startswith("lpips.") for key in model.state_dict())
    with warnings.catch_warnings(record=True) as caught_again:
        warnings.simplefilter("always")
        config.setup(scene_box=scene_box, num_train_data=4, seed_points=seed_cloud())
    assert not [w for w in caught_again if "LPIPS" in str(w.message)], "warned twice in one process"

    model.eval()
    outputs = model.get_outputs_for_camera(make_camera(look_from([2.0, 0.0, 1.0])))
    metrics, images = model.get_image_metrics_and_images(outputs, {"image": torch.rand(H, W, 3)})
    assert set(metrics) == {"psnr", "ssim"}
    assert all(math.isfinite(v) for v in metrics.values())
    assert images["img"].shape == (H, 2 * W, 3)


# -- rendering and training guards -------------------------------------------------------------------------------


def test_outputs_have_splatfacto_keys_and_shapes():
    model = make_model(seed_points=seed_cloud())
    camera = make_camera(look_from([2.0, 0.5, 1.0]))
    model.eval()
    out = model.get_outputs_for_camera(camera)
    assert out["rgb"].shape == (H, W, 3) and out["depth"].shape == (H, W, 1)
    assert out["accumulation"].shape == (H, W, 1) and out["background"].shape == (H, W, 3)
    assert float(out["accumulation"].max()) > 0  # the seed cloud is in view
    model.train()
    model.step, model.optimizers = 0, None
    out = model.get_outputs(camera)
    downscale = 2**model.config.num_downscales
    assert out["rgb"].shape == (H // downscale, W // downscale, 3) and out["depth"] is None
    assert out["rgb"].requires_grad


def test_non_finite_loss_raises_naming_the_step():
    model = make_model(seed_points=seed_cloud(), num_downscales=0, finite_check_every=1)  # SSIM needs >= 11 px
    model.train()
    model.step, model.optimizers = 7, None
    with torch.no_grad():
        model.gauss_params["features_dc"][0] = float("nan")
    camera = make_camera(look_from([2.0, 0.5, 1.0]))
    outputs = model.get_outputs(camera)
    gt = torch.rand(outputs["rgb"].shape)
    with pytest.raises(NonFiniteLossError, match=r"step 7.*main_loss=nan.*features_dc"):
        model.get_loss_dict(outputs, {"image": gt})


def test_loading_a_checkpoint_resizes_parameters_in_place():
    target = make_model(seed_points=seed_cloud(16, seed=1))
    source = make_model(seed_points=seed_cloud(40, seed=2))
    before = {name: param for name, param in target.gauss_params.items()}
    target.load_state_dict(source.state_dict())
    for name, param in target.gauss_params.items():
        assert param is before[name], f"{name} was replaced: optimizers built before loading would lose it"
        torch.testing.assert_close(param.data, source.gauss_params[name].data)
    assert target.num_points == 40


def test_numpy_scalars_load_with_weights_only():
    buffer = io.BytesIO()
    torch.save({"param_groups": [{"lr": np.float64(1e-3)}], "_last_lr": [np.float64(2e-4)]}, buffer)
    buffer.seek(0)
    loaded = torch.load(buffer, weights_only=True)  # gsmsdr_ns.plugin was imported: globals are registered
    assert loaded["param_groups"][0]["lr"] == pytest.approx(1e-3)
    names = {f"{g.__module__}.{g.__name__}" for g in checkpoint_safe_globals()}
    assert any(name.endswith("multiarray.scalar") for name in names) and "numpy.dtype" in names
