import logging
import math

import pytest
import torch

from model_zoo import registry, selectors
from model_zoo.selectors import (
    SelectorConfig,
    SelectorInputs,
    driving_aware_reference,
    driving_score,
    minmax_normalize,
    quality_score,
    rotation_validity,
    topk_indices,
    trajectory_distance,
    trajectory_relevance,
    uniform_spatial_indices,
    union_truncate_pad,
    voxel_ids,
    voxel_topk_indices,
)

VARIANTS = ["driving_aware", "random", "topk_uniform", "topk_uniform_similarity", "voxel_topk"]
UNIT_Q = [1.0, 0.0, 0.0, 0.0]


def build(name: str, **kw):
    return registry.build("selector", name, SelectorConfig(name=name, **kw))


def scene(xyz, opacity=None, trajectory=None, similarity=None) -> SelectorInputs:
    """Gaussians with equal scale and unit rotation; opacity 0.5 unless given."""
    xyz = torch.as_tensor(xyz, dtype=torch.float32).reshape(-1, 3)
    n = xyz.shape[0]
    opacity = torch.full((n,), 0.5) if opacity is None else torch.as_tensor(opacity, dtype=torch.float32)
    return SelectorInputs(
        xyz, torch.full((n, 3), 0.1), torch.tensor(UNIT_Q).repeat(n, 1), opacity, trajectory, similarity
    )


def random_scene(n: int, seed: int = 0, extent=(60.0, 40.0, 6.0)) -> SelectorInputs:
    g = torch.Generator().manual_seed(seed)
    xyz = (torch.rand(n, 3, generator=g) - torch.tensor([0.25, 0.5, 0.2])) * torch.tensor(extent)
    xs = torch.linspace(0, 40, 13)
    return SelectorInputs(
        xyz,
        torch.exp(torch.rand(n, 3, generator=g) * 4 - 4.5),
        torch.randn(n, 4, generator=g),
        torch.rand(n, generator=g),
        trajectory=torch.stack([xs, 0.01 * xs**2], dim=1),
        similarity=torch.rand(n, generator=g),
    )


def chosen(sel) -> list[int]:
    return sel.index[sel.mask].tolist()


def test_registry_lists_the_five_selectors():
    assert [name for _, name in registry.variants("selector")] == VARIANTS


def test_rotation_validity_is_one_for_unit_quaternions_and_hand_computed_otherwise():
    q = torch.tensor([UNIT_Q, [0.5, 0.5, 0.5, 0.5], [2.0, 0.0, 0.0, 0.0], [0.0, 0.6, 0.0, 0.0]])
    torch.testing.assert_close(rotation_validity(q), torch.tensor([1.0, 1.0, 0.5, 1 / 1.4]))


def test_quality_score_hand_computed():
    scale = torch.tensor([[1.0, 1.0, 1.0], [0.5, 0.25, 0.25], [0.1, 0.1, 0.1]])
    rotation = torch.tensor([UNIT_Q, [2.0, 0.0, 0.0, 0.0], UNIT_Q])
    opacity = torch.tensor([0.5, 1.0, 0.0])
    # raw = log(1 + o (|s|_1 + 1) rho): log(1 + 0.5 * 4 * 1) = log 3, log(1 + 1 * 2 * 0.5) = log 2, log(1) = 0
    expected = torch.tensor([1.0, math.log(2) / math.log(3), 0.0])
    torch.testing.assert_close(quality_score(scale, rotation, opacity), expected)


def test_min_max_norm_of_constant_scores_is_all_zeros():
    assert torch.equal(minmax_normalize(torch.full((4,), 3.0)), torch.zeros(4))
    g = scene(torch.zeros(5, 3))
    assert torch.equal(quality_score(g.scale, g.rotation, g.opacity), torch.zeros(5))
    assert minmax_normalize(torch.empty(0)).shape == (0,)


def test_quality_score_names_non_finite_inputs():
    g = scene(torch.zeros(3, 3), opacity=[0.5, float("nan"), 0.2])
    with pytest.raises(ValueError) as e:
        quality_score(g.scale, g.rotation, g.opacity)
    assert str(e.value) == "quality_score: 1 of 3 Gaussians have a non-finite opacity, scale or rotation"


def test_trajectory_distance_relevance_and_driving_score_hand_computed():
    xyz = torch.tensor([[3.0, 4.0, 100.0], [10.0, -1.0, 0.0]])
    waypoints = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
    d = trajectory_distance(xyz, waypoints)  # z is ignored (pi_xy)
    torch.testing.assert_close(d, torch.tensor([5.0, 1.0]))
    t = trajectory_relevance(d, sigma_traj=5.0)
    torch.testing.assert_close(t, torch.tensor([math.exp(-0.5), math.exp(-1 / 50)]))
    assert torch.equal(trajectory_distance(xyz, None), torch.full((2,), math.inf))
    far = trajectory_relevance(torch.tensor([100.0, math.inf]), 5.0)  # exponent clamped at -80: no denormals
    assert torch.equal(far, torch.full((2,), math.exp(-80.0), dtype=torch.float32))
    torch.testing.assert_close(driving_score(torch.tensor([1.0, 0.2]), torch.tensor([0.0, 1.0]), 1.0, 3.0),
                               torch.tensor([0.25, 0.8]))  # fmt: skip


def test_trajectory_distance_chunks_agree_with_the_full_matrix(monkeypatch):
    monkeypatch.setattr(selectors, "_CHUNK", 7)
    g = random_scene(100)
    full = torch.cdist(g.xyz[:, :2], g.trajectory, compute_mode="donot_use_mm_for_euclid_dist").amin(dim=1)
    torch.testing.assert_close(trajectory_distance(g.xyz, g.trajectory), full)


def test_trajectory_term_selects_gaussians_near_the_path_first():
    # Equal quality everywhere; 20 far Gaussians (y = 30 m) come first so index tie-breaking would pick them.
    far = [[2.0 * i, 30.0, 0.0] for i in range(20)]
    near = [[2.0 * i, 0.5 * (-1) ** i, 0.0] for i in range(20)]
    path = torch.stack([torch.linspace(0, 40, 13), torch.zeros(13)], dim=1)
    g = scene(far + near, trajectory=path)
    assert sorted(chosen(build("driving_aware", k_c=20)(g))) == list(range(20, 40))
    assert sorted(chosen(build("driving_aware", k_c=20, coverage_first=False)(g))) == list(range(20, 40))
    assert sorted(chosen(build("voxel_topk", k_c=20)(g))) == list(range(20))  # no trajectory term: ties by index


def coverage_scene() -> tuple[SelectorInputs, list[int]]:
    """10 occupied 2 m voxels: a 100-Gaussian cluster of high opacity in voxel 0, 9 low-opacity singletons."""
    g = torch.Generator().manual_seed(3)
    cluster = torch.rand(100, 3, generator=g) * 1.9 + 0.05
    singles = torch.tensor([[2.0 * i + 1, 10.0 + i, 1.0] for i in range(9)])
    opacity = [0.9 + 0.1 * i / 100 for i in range(100)] + [0.05] * 9
    path = torch.tensor([[0.0, 0.0], [2.0, 0.0]])
    g = scene(torch.cat([cluster, singles]), opacity=opacity, trajectory=path)
    voxel = voxel_ids(g.xyz, 2.0)[0].tolist()
    assert len(set(voxel)) == 10
    return g, voxel


@pytest.mark.parametrize("name", ["voxel_topk", "driving_aware"])
@pytest.mark.parametrize("k_c", [10, 16])
def test_voxel_branch_reaches_every_occupied_voxel(name, k_c):
    g, voxel = coverage_scene()
    picked = chosen(build(name, k_c=k_c)(g))
    assert len(picked) == k_c
    assert len({voxel[i] for i in picked}) == 10
    assert sum(i < 100 for i in picked) == k_c - 9  # the rest of the budget goes to the cluster's best


def test_literal_union_truncation_loses_the_voxel_branch():
    # The paper's literal rule (top K_c of TopK ∪ VoxelTopK by S) equals TopK(S, K_c) whenever N >= K_c.
    g, voxel = coverage_scene()
    picked = chosen(build("voxel_topk", k_c=16, coverage_first=False)(g))
    assert len({voxel[i] for i in picked}) == 1


def test_voxel_topk_indices_keeps_the_best_of_each_voxel_then_the_top_k():
    xyz = torch.tensor([[0.5, 0.5, 0.5], [1.5, 0.5, 0.5], [2.5, 0.5, 0.5], [3.5, 0.5, 0.5], [-0.5, 0.0, 0.0]])
    score = torch.tensor([0.2, 0.9, 0.4, 0.4, 0.1])
    # voxels (size 2): {0, 1} best 1, {2, 3} tie -> lower index 2, {4} alone
    assert voxel_topk_indices(xyz, score, 5, 2.0).tolist() == [1, 2, 4]
    assert voxel_topk_indices(xyz, score, 2, 2.0).tolist() == [1, 2]
    assert topk_indices(score, 4).tolist() == [1, 2, 3, 0]


def test_topk_indices_orders_negative_scores_and_breaks_ties_by_index():
    score = torch.tensor([0.5, -1.0, -0.0, 0.0, 2.0, -3.0, 0.5])
    assert topk_indices(score, 7).tolist() == [4, 0, 6, 2, 3, 1, 5]  # -0.0 == 0.0: a tie, lower index first


@pytest.mark.parametrize("sample_first", [True, False])
def test_sampled_topk_equals_the_full_topk(monkeypatch, sample_first):
    monkeypatch.setattr(selectors, "_SAMPLE_MIN", 64)
    monkeypatch.setattr(selectors, "_SAMPLE_SIZE", 16)
    g = torch.Generator().manual_seed(0)
    score = torch.rand(1000, generator=g)
    if not sample_first:  # the strided sample (every 62nd) holds the 17 largest: too few pass, full topk fallback
        score[::62] += 10
    expected = torch.sort(score, descending=True).indices[:50]
    assert torch.equal(topk_indices(score, 50), expected)


def test_voxel_ids_sparse_path_matches_the_dense_one(monkeypatch):
    g = random_scene(3000, seed=5)
    dense = build("driving_aware", k_c=300, voxel_size=3.0)(g)
    monkeypatch.setattr(selectors, "_DENSE_CELLS_PER_GAUSSIAN", 0)
    monkeypatch.setattr(selectors, "_DENSE_CELLS_MIN", 0)
    ids, cells = voxel_ids(g.xyz, 3.0)
    assert cells == len(set(ids.tolist()))  # compacted to the occupied voxels
    sparse = build("driving_aware", k_c=300, voxel_size=3.0)(g)
    assert torch.equal(dense.index, sparse.index)


def test_voxel_ids_names_non_finite_centres():
    with pytest.raises(ValueError) as e:
        voxel_ids(torch.tensor([[0.0, 0.0, 0.0], [float("inf"), 0.0, 1.0]]), 2.0)
    assert str(e.value) == "voxel_ids: 1 of 2 Gaussian centres are not finite"


def test_union_truncation_keeps_the_top_by_score_and_pads():
    score = torch.tensor([0.1, 0.9, 0.5, 0.7, 0.3])
    branches = [torch.tensor([0, 1]), torch.tensor([2, 3, 1])]
    sel = union_truncate_pad(score, 3, branches)
    assert sel.index.tolist() == [1, 3, 2]
    assert sel.mask.tolist() == [True, True, True]
    assert union_truncate_pad(score, 3, branches, keep_first=torch.tensor([0])).index.tolist() == [1, 3, 0]
    padded = union_truncate_pad(score, 6, branches)
    assert padded.index.tolist() == [1, 3, 2, 0, 0, 0]
    assert padded.mask.tolist() == [True, True, True, True, False, False]


@pytest.mark.parametrize("name", VARIANTS)
def test_padding_when_k_c_exceeds_n(name, caplog):
    g = random_scene(5)
    with caplog.at_level(logging.WARNING, logger="model_zoo.selectors"):
        sel = build(name, k_c=8)(g)
    assert sel.index.shape == (8,) and sel.index.dtype == torch.int64 and sel.mask.dtype == torch.bool
    assert int(sel.mask.sum()) == 5
    assert sorted(chosen(sel)) == [0, 1, 2, 3, 4]
    assert sel.index[~sel.mask].tolist() == [0, 0, 0]
    assert sel.mask.tolist() == [True] * 5 + [False] * 3  # real candidates first
    assert "5 candidate(s) for K_c=8 from N=5 Gaussians; padding 3 invalid token(s)" in caplog.text


@pytest.mark.parametrize("name", VARIANTS)
def test_empty_scene_is_all_padding(name):
    g = random_scene(0)
    sel = build(name, k_c=4)(g)
    assert sel.index.tolist() == [0, 0, 0, 0]
    assert sel.mask.tolist() == [False] * 4


@pytest.mark.parametrize("name", ["driving_aware", "voxel_topk", "topk_uniform", "topk_uniform_similarity"])
def test_scored_selectors_order_by_descending_score_without_duplicates(name):
    g = random_scene(2000, seed=1)
    sel = build(name, k_c=300, voxel_size=4.0)(g)
    assert int(sel.mask.sum()) == 300
    assert len(set(chosen(sel))) == 300
    s = build("driving_aware").score(g) if name == "driving_aware" else quality_score(g.scale, g.rotation, g.opacity)
    ranked = s[sel.index]
    assert bool((ranked[:-1] >= ranked[1:]).all())


def test_random_is_deterministic_per_seed_without_duplicates():
    g = random_scene(1000)
    sel = build("random", k_c=100, seed=7)
    a, b = sel(g), sel(g)
    assert torch.equal(a.index, b.index)
    assert len(set(chosen(a))) == 100 and int(a.mask.sum()) == 100
    assert torch.equal(sel(g, torch.Generator().manual_seed(7)).index, a.index)
    assert not torch.equal(sel(g, torch.Generator().manual_seed(8)).index, a.index)
    assert not torch.equal(build("random", k_c=100, seed=8)(g).index, a.index)


def test_uniform_spatial_sampling_visits_every_voxel_before_repeating_one():
    xyz = torch.cat([torch.full((5, 3), 2.0 * i + 1) for i in range(10)])  # 10 voxels of 5 Gaussians each
    gen = torch.Generator().manual_seed(0)
    voxel = voxel_ids(xyz, 2.0)[0]
    first = uniform_spatial_indices(xyz, 10, 2.0, gen)
    assert len(set(voxel[first].tolist())) == 10
    more = uniform_spatial_indices(xyz, 15, 2.0, gen)
    assert len(set(more.tolist())) == 15 and len(set(voxel[more[:10]].tolist())) == 10
    pool = torch.arange(0, 50, 5)  # one Gaussian per voxel
    assert sorted(uniform_spatial_indices(xyz, 20, 2.0, gen, candidates=pool).tolist()) == pool.tolist()


def test_topk_uniform_budget_splits_between_ranked_and_uniform():
    g = random_scene(1000, seed=2)
    q = quality_score(g.scale, g.rotation, g.opacity)
    voxel = voxel_ids(g.xyz, 10.0)[0].tolist()
    assert len(set(voxel)) == 56
    picked = set(chosen(build("topk_uniform", k_c=40, uniform_fraction=0.5, voxel_size=10.0)(g)))
    top = set(topk_indices(q, 20).tolist())
    assert len(picked) == 40 and top <= picked
    assert len({voxel[i] for i in picked - top}) == 20  # the uniform half: one per voxel, 20 distinct voxels


def test_topk_uniform_similarity_takes_the_top_similarity_share():
    g = random_scene(1000, seed=2)
    q = quality_score(g.scale, g.rotation, g.opacity)
    picked = set(chosen(build("topk_uniform_similarity", k_c=40, uniform_fraction=0.5, similarity_fraction=0.25)(g)))
    top_sim = set(topk_indices(g.similarity, 10).tolist())
    assert len(picked) == 40 and top_sim <= picked
    q_ranked = [i for i in topk_indices(q, 1000).tolist() if i not in top_sim][:10]
    assert set(q_ranked) <= picked


def test_topk_uniform_similarity_without_similarity_names_the_selector():
    g = random_scene(10)
    g.similarity = None
    with pytest.raises(ValueError) as e:
        build("topk_uniform_similarity")(g)
    assert str(e.value) == (
        "selector 'topk_uniform_similarity' needs SelectorInputs.similarity ([N] text-Gaussian similarity), got None"
    )


def test_config_and_input_errors_name_the_problem():
    with pytest.raises(ValueError) as e:
        SelectorConfig(name="voxel_topk", voxel_size=0.0)
    assert str(e.value) == "SelectorConfig 'voxel_topk': voxel_size must be > 0 metres, got 0.0"
    with pytest.raises(ValueError) as e:
        build("topk_uniform_similarity", uniform_fraction=0.9, similarity_fraction=0.25)
    assert str(e.value) == (
        "selector 'topk_uniform_similarity': similarity_fraction (0.25) must fit in the ranked share "
        "1 - uniform_fraction (0.09999999999999998)"
    )
    g = random_scene(4)
    g.trajectory = torch.zeros(3, 3)
    with pytest.raises(ValueError) as e:
        build("driving_aware")(g)
    assert str(e.value) == "selector 'driving_aware': trajectory must be [T, 2] ground-plane waypoints, got [3, 3]"
    g = random_scene(4)
    g.opacity = torch.zeros(4, 1)
    with pytest.raises(ValueError, match=r"^selector 'random': inputs must be xyz \[N, 3\].*\(opacity is off\)$"):
        build("random")(g)


def test_driving_aware_without_trajectory_ranks_by_quality_and_warns_once(monkeypatch, caplog):
    monkeypatch.setattr(selectors, "_warned_no_trajectory", False)
    g = random_scene(2000, seed=4)
    g.trajectory = None
    with caplog.at_level(logging.WARNING, logger="model_zoo.selectors"):
        a = build("driving_aware", k_c=200)(g)
        g.trajectory = torch.empty(0, 2)
        b = build("driving_aware", k_c=200)(g)
    assert caplog.text.count("no trajectory given, so T_i = 0") == 1
    expected = build("voxel_topk", k_c=200)(g)
    assert torch.equal(a.index, expected.index) and torch.equal(b.index, expected.index)


@pytest.mark.parametrize(
    ("k_c", "voxel_size", "coverage_first"), [(256, 4.0, True), (256, 1.0, True), (700, 4.0, False)]
)
def test_driving_aware_matches_the_numpy_reference(k_c, voxel_size, coverage_first):
    g = random_scene(5000, seed=11)
    cfg = SelectorConfig(k_c=k_c, voxel_size=voxel_size, coverage_first=coverage_first)
    sel = build("driving_aware", k_c=k_c, voxel_size=voxel_size, coverage_first=coverage_first)(g)
    ref = driving_aware_reference(g, cfg)
    assert int(sel.mask.sum()) == len(ref) == k_c
    assert set(chosen(sel)) == set(ref.tolist())


# ---- the path of T_i: the planned route (issue 17) --------------------------------------------------------------
def _pose(x: float, y: float, yaw: float):
    import numpy as np

    m = np.eye(4)
    m[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    m[:2, 3] = [x, y]
    return m


def test_route_path_runs_ahead_of_the_ego_along_the_route_in_its_lane():
    import numpy as np

    route = np.stack([np.arange(-10.0, 100.0), np.full(110, -1.75)], 1)  # a lane centreline along world +x
    on_lane = selectors.route_path(route, _pose(20.0, -1.75, 0.0), ahead_m=5.0)
    np.testing.assert_allclose(on_lane, [[0, 0], [1, 0], [2, 0], [3, 0], [4, 0], [5, 0]], atol=1e-5)
    # 3.5 m left of the route (after a lane change), turned 90 degrees: the path keeps the ego's lane, ahead of it
    # in the world, which the ego frame sees on its right
    left = selectors.route_path(route, _pose(20.0, 1.75, math.pi / 2), ahead_m=2.0)
    np.testing.assert_allclose(left, [[0, 0], [0, -1], [0, -2]], atol=1e-5)


def test_route_path_follows_a_bend_and_stops_at_the_routes_end():
    import numpy as np

    r = 50.0
    th = np.linspace(0, 1.0, 200)
    route = np.stack([r * np.sin(th), r - r * np.cos(th)], 1)  # bends left
    path = selectors.route_path(route, _pose(0.0, 0.0, 0.0), ahead_m=20.0)
    assert path.shape == (21, 2)
    np.testing.assert_allclose(np.hypot(path[:, 0], path[:, 1] - r), r, atol=0.02)  # on the circle
    assert path[-1, 1] > 3.5  # bent to the left
    end = selectors.route_path(route, _pose(*route[-41], 0.0), ahead_m=20.0)  # 40 x 0.25 m of route left
    assert len(end) == 11 and abs(np.hypot(*end[-1]) - 2 * r * math.sin(0.1)) < 0.01  # a 10 m arc's chord


def test_route_path_names_a_degenerate_route():
    import numpy as np

    with pytest.raises(ValueError) as e:
        selectors.route_path(np.array([[1.0, 2.0], [1.0, 2.0]]), _pose(0, 0, 0), ahead_m=10.0)
    assert str(e.value) == "route_path: the route needs >= 2 distinct finite points, got 1"


def test_selector_path_is_a_checked_enum_defaulting_to_the_route():
    assert SelectorConfig().path == "route" and SelectorConfig(path="extrapolated").path == "extrapolated"
    with pytest.raises(ValueError) as e:
        SelectorConfig(name="driving_aware", path="future")
    assert str(e.value) == "SelectorConfig 'driving_aware': path must be one of ['route', 'extrapolated'], got 'future'"
