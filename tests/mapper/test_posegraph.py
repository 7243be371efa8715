"""The Sim(3) pose graph of mapper/posegraph.py: a loop closure removes the drift of a ring,
scale included, and bad input fails clearly."""

import math

import pytest
import torch

from dimslam.common.errors import DimslamError
from dimslam.common.geometry import pose, sim3
from dimslam.mapper import posegraph
from dimslam.mapper.posegraph import Edge, odometry_edges, solve_pose_graph

F64 = torch.float64


def ring(n: int = 40, radius: float = 5.0) -> torch.Tensor:
    """Ground-truth world-from-node poses (n, 4, 4) around a circle, each turned by its angle."""
    phi = torch.arange(n, dtype=F64) * 2 * math.pi / n
    w = torch.zeros(n, 3, dtype=F64)
    w[:, 2] = phi
    t = torch.stack([radius * phi.cos(), radius * phi.sin(), torch.zeros_like(phi)], dim=-1)
    return sim3.from_pose(pose.make_pose(pose.exp_so3(w), t))


def drifted(truth: torch.Tensor) -> torch.Tensor:
    """Chain the true steps with a small rotation drift and 1 % scale shrink per step."""
    steps = sim3.compose(sim3.invert(truth[:-1]), truth[1:])
    drift = sim3.from_pose(pose.exp_se3(torch.tensor([0, 0, 0, 0.01, 0.005, 0], dtype=F64)), 0.99)
    chain = [truth[0]]
    for step in steps:
        chain.append(chain[-1] @ step @ drift)
    return torch.stack(chain)


def end_to_start_error(nodes: torch.Tensor, truth: torch.Tensor) -> float:
    """Translation error of the last node's estimate of the first, in the last node's frame."""
    rel = sim3.invert(nodes[-1]) @ nodes[0]
    return (rel[:3, 3] - (sim3.invert(truth[-1]) @ truth[0])[:3, 3]).norm().item()


def loop_edge(truth: torch.Tensor, weight: float = 1.0) -> Edge:
    return Edge(len(truth) - 1, 0, sim3.invert(truth[-1]) @ truth[0], weight)


def random_nodes(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return sim3.exp_sim3(0.5 * torch.randn(n, 7, generator=g, dtype=F64))


def test_consistent_edges_cost_nothing_and_move_nothing():
    truth = random_nodes(12)
    edges = odometry_edges(truth) + [
        Edge(a, b, sim3.invert(truth[a]) @ truth[b], 5.0) for a, b in ((0, 7), (11, 3), (4, 9))
    ]
    result = solve_pose_graph(truth, edges)
    assert result.initial_cost < 1e-20
    assert result.final_cost < 1e-20
    assert torch.allclose(result.nodes, truth, atol=1e-12)


def test_loop_closure_removes_rotation_and_scale_drift_of_a_ring():
    truth = ring()
    estimate = drifted(truth)
    scales = sim3.scale_of(estimate)
    assert scales[-1] == pytest.approx(0.99**39)  # ~30 % smaller at the end
    before = end_to_start_error(estimate, truth)
    assert before > 2.0  # far from the start

    result = solve_pose_graph(estimate, odometry_edges(estimate) + [loop_edge(truth)])

    assert result.final_cost < 0.01 * result.initial_cost
    assert end_to_start_error(result.nodes, truth) <= before / 5
    # The scale correction is spread along the chain, not dumped on the last node: it grows
    # steadily from node 0 (fixed) and reaches about half at the middle.
    correction = (sim3.scale_of(result.nodes) / scales).log()
    assert correction[0] == 0.0
    assert (correction.diff() > 0).all()
    assert 0.35 < correction[20] / correction[-1] < 0.65
    assert sim3.scale_of(result.nodes[-1]) > 0.95  # the loop says: same scale as node 0


def test_a_heavier_loop_edge_is_trusted_more():
    truth = ring()
    estimate = drifted(truth)
    errors = [
        end_to_start_error(
            solve_pose_graph(estimate, odometry_edges(estimate) + [loop_edge(truth, w)]).nodes,
            truth,
        )
        for w in (1.0, 100.0)
    ]
    assert errors[1] < 0.1 * errors[0]


def test_fixed_nodes_stay_exactly_fixed():
    truth = random_nodes(15, seed=1)
    noise = 0.05 * torch.randn(15, 7, generator=torch.Generator().manual_seed(4), dtype=F64)
    noise[[0, 7]] = 0.0
    start = truth @ sim3.exp_sim3(noise)
    start[[0, 7]] = truth[[0, 7]]
    edges = odometry_edges(truth) + [Edge(14, 0, sim3.invert(truth[14]) @ truth[0])]
    result = solve_pose_graph(start, edges, fixed=(0, 7))
    assert torch.equal(result.nodes[[0, 7]], truth[[0, 7]])
    assert result.initial_cost > 0.01 and result.final_cost < 1e-20
    assert torch.allclose(result.nodes, truth, atol=1e-9)


def test_nothing_to_do_returns_the_input():
    nodes = random_nodes(5)
    for edges, fixed in (([], (0,)), (odometry_edges(nodes[[0, 2, 1, 4, 3]]), range(5))):
        result = solve_pose_graph(nodes, edges, fixed=tuple(fixed))
        assert torch.equal(result.nodes, nodes) and result.iterations == 0
        assert result.final_cost == result.initial_cost


def test_jacobians_match_finite_differences_of_the_right_perturbation():
    nodes = random_nodes(4, seed=2)
    i, j = torch.tensor([0, 2, 3]), torch.tensor([1, 0, 1])
    S_ij_inv = sim3.invert(random_nodes(3, seed=3))
    J = posegraph._jacobians(nodes, i, j, S_ij_inv)
    h = 1e-6
    for k in range(14):
        d = torch.zeros(3, 14, dtype=F64)
        d[:, k] = h
        plus = posegraph._residuals(nodes, i, j, S_ij_inv, d)
        minus = posegraph._residuals(nodes, i, j, S_ij_inv, -d)
        assert torch.allclose(J[:, :, k], (plus - minus) / (2 * h), atol=1e-7)


def _edge(i=0, j=1, S=None, weight=1.0):
    return Edge(i, j, torch.eye(4, dtype=F64) if S is None else S, weight)


@pytest.mark.parametrize(
    "edges,fixed,message",
    [
        ([_edge(0, 3)], (0,), "edge 0 \\(0 -> 3\\)"),
        ([_edge(), _edge(-1, 2)], (0,), "edge 1"),
        ([_edge(1, 1)], (0,), "edge 0"),
        ([_edge(S=torch.full((4, 4), math.nan, dtype=F64))], (0,), "edges \\[0\\]"),
        ([_edge(S=-torch.eye(4, dtype=F64))], (0,), "edges \\[0\\]"),
        ([_edge(S=torch.eye(3, dtype=F64))], (0,), "not \\(4, 4\\)"),
        ([_edge(weight=0.0)], (0,), "weight"),
        ([_edge()], (5,), "fixed"),
    ],
)
def test_bad_input_raises_a_clear_error(edges, fixed, message):
    with pytest.raises(DimslamError, match=message):
        solve_pose_graph(random_nodes(3), edges, fixed=fixed)


def test_bad_nodes_raise_a_clear_error():
    nodes = random_nodes(3)
    nodes[1, 0, 3] = math.inf
    with pytest.raises(DimslamError, match="nodes \\[1\\]"):
        solve_pose_graph(nodes, [_edge()])
    with pytest.raises(DimslamError, match="\\(N, 4, 4\\)"):
        solve_pose_graph(torch.eye(4, dtype=F64), [])
