import numpy as np
import torch

from model_zoo.quaternion import quat_mul, quat_to_rotmat
from pipelines.data import layout


def test_the_product_of_quaternions_is_the_product_of_their_rotations():
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(8, 4, generator=g, dtype=torch.float64), torch.randn(8, 4, generator=g, dtype=torch.float64)
    a, b = a / a.norm(dim=1, keepdim=True), b / b.norm(dim=1, keepdim=True)
    torch.testing.assert_close(quat_to_rotmat(quat_mul(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b))
    torch.testing.assert_close(quat_to_rotmat(torch.tensor([[2.0, 0, 0, 0]])), torch.eye(3)[None])  # normalised


def test_the_data_layers_numpy_pair_agrees_with_the_torch_one():
    # pipelines.data.layout keeps numpy quaternion code (the data layer imports no model code): the same numbers
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=4), rng.normal(size=(5, 4))
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b, axis=1, keepdims=True)
    want = quat_mul(torch.from_numpy(np.broadcast_to(a, b.shape).copy()), torch.from_numpy(b)).numpy()
    np.testing.assert_allclose(layout._quat_mul(a, b), want, atol=1e-12)
    r = quat_to_rotmat(torch.from_numpy(a)).numpy()
    q = layout.matrix_to_quat_wxyz(r)
    np.testing.assert_allclose(q, a if a[0] >= 0 else -a, atol=1e-12)
