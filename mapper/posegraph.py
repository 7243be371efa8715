"""A Sim(3) pose graph over keyframes, solved by Levenberg-Marquardt: loop closure for a map
whose scale drifts (monocular), after Strasdat et al., "Scale Drift-Aware Large Scale
Monocular SLAM" (RSS 2010).

Nodes are world-from-node similarities `S_k` (`common/geometry/sim3.py`). An edge (i, j)
measures `S_ij ~ S_i^-1 S_j`; its residual is `r = log(S_ij^-1 S_i^-1 S_j)` (7-vector) and the
cost is `sum_edges weight * |r|^2 / 2`. Updates are right (body-frame) perturbations,
`S_k <- S_k exp(delta_k)`, as `pose.retract` does for SE(3).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from dimslam.common.errors import DimslamError
from dimslam.common.geometry import sim3

# Marquardt's damping: start, factor per failed / successful step, and the value past which a
# step cannot help any more (the gradient is at rounding level).
_LAMBDA_INIT, _LAMBDA_UP, _LAMBDA_DOWN, _LAMBDA_MAX = 1e-4, 10.0, 10.0, 1e10


@dataclass(frozen=True, eq=False)  # eq=False: tensor fields make == ambiguous
class Edge:
    """A relative measurement between two nodes.

    Attributes:
        i, j: node indices.
        S_ij: (4, 4) measured Sim(3) of node j in node i's frame, ideally `S_i^-1 S_j`.
        weight: scalar information weight (> 0), e.g. larger for trusted loop closures.
    """

    i: int
    j: int
    S_ij: torch.Tensor
    weight: float = 1.0


@dataclass
class PoseGraphResult:
    """nodes: (N, 4, 4) float64 world-from-node Sim(3); costs before and after; LM iterations."""

    nodes: torch.Tensor
    initial_cost: float
    final_cost: float
    iterations: int


def odometry_edges(nodes: torch.Tensor) -> list[Edge]:
    """Edges `(k, k + 1)` from consecutive estimates `(N, 4, 4)`: `S_k^-1 S_k+1`, weight 1."""
    rel = sim3.compose(sim3.invert(nodes[:-1]), nodes[1:])
    return [Edge(k, k + 1, rel[k]) for k in range(len(rel))]


def _residuals(nodes, i, j, S_ij_inv, delta=None) -> torch.Tensor:
    """Residuals (E, 7) `log(S_ij^-1 S_i^-1 S_j)`, with nodes i, j moved by `delta` (E, 14)."""
    S_i, S_j = nodes[i], nodes[j]
    if delta is not None:
        S_i, S_j = S_i @ sim3.exp_sim3(delta[:, :7]), S_j @ sim3.exp_sim3(delta[:, 7:])
    return sim3.log_sim3(S_ij_inv @ sim3.invert(S_i) @ S_j)


def _jacobians(nodes, i, j, S_ij_inv) -> torch.Tensor:
    """d r_e / d (delta_i, delta_j) at 0, (E, 7, 14), by autograd.

    Edges are independent, so one backward pass per residual component gives that row for
    every edge at once: 7 batched passes, ~5x faster than `vmap(jacrev)` at 400 edges.
    """
    delta = torch.zeros(len(i), 14, dtype=nodes.dtype, requires_grad=True)
    with torch.enable_grad():
        r = _residuals(nodes, i, j, S_ij_inv, delta)
        rows = [torch.autograd.grad(r[:, k].sum(), delta, retain_graph=k < 6)[0] for k in range(7)]
    return torch.stack(rows, dim=1)


def _normal_equations(J, r, w, cols, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Newton H (m, m) and gradient g (m,) over the free coordinates.

    Args:
        J: (E, 7, 14) Jacobians; r: (E, 7) residuals; w: (E,) weights.
        cols: (E, 14) each Jacobian column's index among the m free coordinates, -1 if fixed.
    """
    JtW = J.mT * w[:, None, None]
    ok = cols >= 0
    pair = ok[:, :, None] & ok[:, None, :]
    rows_of, cols_of = cols[:, :, None].expand_as(pair), cols[:, None, :].expand_as(pair)
    H = torch.zeros(m, m, dtype=J.dtype)
    H.index_put_((rows_of[pair], cols_of[pair]), (JtW @ J)[pair], accumulate=True)
    g = torch.zeros(m, dtype=J.dtype)
    g.index_put_((cols[ok],), (JtW @ r[:, :, None])[..., 0][ok], accumulate=True)
    return H, g


def _costs(nodes, i, j, S_ij_inv, w) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals (E, 7) and the total cost of all edges."""
    r = _residuals(nodes, i, j, S_ij_inv)
    return r, 0.5 * (w * (r * r).sum(-1)).sum()


def _check_matrices(what: str, S: torch.Tensor) -> None:
    """Raise unless every `(K, 4, 4)` matrix is finite with a positive scale."""
    bad = ~torch.isfinite(S).flatten(1).all(1)
    bad |= ~(sim3.scale_of(torch.where(bad[:, None, None], 1.0, S)) > 0)
    if bad.any():
        raise DimslamError(f"pose graph: {what} {bad.nonzero()[:, 0].tolist()} are not Sim(3)")


def _validate(nodes: torch.Tensor, edges: Sequence[Edge], fixed: Sequence[int]) -> torch.Tensor:
    """Check the input; return the edges' measurements stacked (E, 4, 4) in float64."""
    if nodes.ndim != 3 or nodes.shape[1:] != (4, 4):
        raise DimslamError(f"pose graph: nodes must be (N, 4, 4), got {tuple(nodes.shape)}")
    _check_matrices("nodes", nodes)
    n = len(nodes)
    for k, e in enumerate(edges):
        if not (0 <= e.i < n and 0 <= e.j < n) or e.i == e.j:
            raise DimslamError(f"pose graph: edge {k} ({e.i} -> {e.j}) needs two of {n} nodes")
        if tuple(e.S_ij.shape) != (4, 4):
            raise DimslamError(f"pose graph: edge {k} S_ij is {tuple(e.S_ij.shape)}, not (4, 4)")
        if not (math.isfinite(e.weight) and e.weight > 0):
            raise DimslamError(f"pose graph: edge {k} has weight {e.weight}, not > 0")
    if any(not 0 <= k < n for k in fixed):
        raise DimslamError(f"pose graph: fixed nodes {list(fixed)} outside 0..{n - 1}")
    S_ij = torch.stack([e.S_ij.detach().cpu().double() for e in edges]) if edges else nodes[:0]
    _check_matrices("edges", S_ij)
    return S_ij


def solve_pose_graph(
    nodes: torch.Tensor,
    edges: Sequence[Edge],
    fixed: Sequence[int] = (0,),
    iters: int = 30,
    tol: float = 1e-10,
) -> PoseGraphResult:
    """Minimize `sum weight * |log(S_ij^-1 S_i^-1 S_j)|^2 / 2` over the free nodes.

    Each LM iteration builds dense normal equations (7N x 7N) from per-edge Jacobians
    (autograd, batched over edges), drops the fixed nodes, and solves by Cholesky; nodes are
    updated as `S_k <- S_k exp(delta_k)`, delta ordered `(rho, omega, sigma)`.

    Args:
        nodes: (N, 4, 4) world-from-node Sim(3) estimates, any float dtype or device (solved
            on the CPU in float64: the dense Cholesky of a few thousand rows is cheap there).
        edges: the measurements.
        fixed: nodes held exactly (the gauge; node 0 by default). Empty leaves 7 free dof,
            which the damping keeps finite.
        iters: at most this many LM iterations (accepted or rejected steps).
        tol: stop when the largest step entry, the gradient, or the relative decrease of the
            cost falls below it.

    Returns:
        The optimized nodes (CPU, float64), costs before and after, and the iterations run.
        With no edges or every node fixed, the input nodes unchanged and zero iterations.

    Raises:
        DimslamError: malformed nodes, edges referencing missing nodes, non-finite or
            non-positive-scale matrices, weights that are not > 0, fixed indices out of range.
    """
    fixed = list(fixed)
    nodes = nodes.detach().to("cpu", torch.float64, copy=True)
    S_ij = _validate(nodes, edges, fixed)
    n = len(nodes)
    free = torch.ones(n, dtype=torch.bool)
    free[fixed] = False
    if not edges:
        return PoseGraphResult(nodes, 0.0, 0.0, 0)
    i = torch.tensor([e.i for e in edges])
    j = torch.tensor([e.j for e in edges])
    w = torch.tensor([e.weight for e in edges], dtype=torch.float64)
    S_ij_inv = sim3.invert(S_ij)
    r, cost = _costs(nodes, i, j, S_ij_inv, w)
    initial = cost.item()
    if not free.any():
        return PoseGraphResult(nodes, initial, initial, 0)

    keep = free.repeat_interleave(7)
    col = torch.where(keep, keep.cumsum(0) - 1, -1)  # global coordinate -> free coordinate
    seven = torch.arange(7)
    cols = col[torch.cat([7 * i[:, None] + seven, 7 * j[:, None] + seven], dim=1)]
    lam, it, need_jacobian = _LAMBDA_INIT, 0, True
    while it < iters:
        if need_jacobian:
            J = _jacobians(nodes, i, j, S_ij_inv)  # (E, 7, 14)
            H, g = _normal_equations(J, r, w, cols, int(keep.sum()))
            if g.abs().max() < tol:
                break
        it += 1
        d = H.diagonal()
        # Marquardt's scaled damping; the floor keeps nodes without edges solvable.
        damped = torch.diagonal_scatter(H, (1 + lam) * d + 1e-12 * (1 + d.max()))
        L, info = torch.linalg.cholesky_ex(damped)
        if info.item() == 0:
            step = torch.zeros(n, 7, dtype=torch.float64)
            y = torch.linalg.solve_triangular(L, -g[:, None], upper=False)
            step[free] = torch.linalg.solve_triangular(L.mT, y, upper=True).view(-1, 7)
            trial = nodes @ sim3.exp_sim3(step)
            trial[~free] = nodes[~free]  # bit-exact, not times exp(0)
            r_new, cost_new = _costs(trial, i, j, S_ij_inv, w)
            if cost_new < cost:
                decrease = (cost - cost_new).item()
                nodes, r, cost, need_jacobian = trial, r_new, cost_new, True
                lam = max(lam / _LAMBDA_DOWN, 1e-12)
                if step.abs().max() < tol or decrease <= tol * cost.item():
                    break
                continue
            if step.abs().max() < tol:
                break
        need_jacobian = False
        lam *= _LAMBDA_UP
        if lam > _LAMBDA_MAX:
            break
    return PoseGraphResult(nodes, initial, cost.item(), it)
