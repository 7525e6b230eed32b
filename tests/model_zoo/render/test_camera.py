import numpy as np
import pytest
import torch

from model_zoo.render import Camera


def test_from_numpy_gives_float32_tensors_and_keeps_values():
    K = np.array([[100.0, 0, 80], [0, 100.0, 48], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[:3, 3] = [1.0, 2.0, 3.0]
    cam = Camera.from_numpy(K, w2c, 160, 96, near=0.1)
    assert cam.K_33.dtype == torch.float32 and cam.world2cam_44.dtype == torch.float32
    assert cam.world2cam_44[:3, 3].tolist() == [1.0, 2.0, 3.0]
    assert (cam.width, cam.height, cam.near, cam.far) == (160, 96, 0.1, 1000.0)


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"K_33": torch.eye(4)}, r"Camera.K_33 must have shape \(3, 3\), got \(4, 4\)"),
        ({"world2cam_44": torch.eye(3)}, r"Camera.world2cam_44 must have shape \(4, 4\), got \(3, 3\)"),
        ({"width": 0}, r"Camera.width must be a positive int, got 0"),
        ({"near": 2.0, "far": 1.0}, r"0 < near < far, got near=2.0, far=1.0"),
        ({"K_33": torch.full((3, 3), float("nan"))}, r"contain NaN or inf"),
    ],
)
def test_bad_camera_names_the_field(kw, message):
    args = {"K_33": torch.eye(3), "world2cam_44": torch.eye(4), "width": 8, "height": 6} | kw
    with pytest.raises(ValueError, match=message):
        Camera(**args)
