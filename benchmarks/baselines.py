"""Two baselines for the VBD sweep of `solver.Simulation`, for the benchmarks only.

* `JacobiSweep`: the same per-vertex 3x3 Newton update, but all free vertices at once from the
  same old positions (no colouring), written into a temporary field and then applied. It reuses the
  simulation's arrays and `solver.vbd.vertex_solve.force_hessian`, so the only difference to VBD is the ordering.
  `omega` < 1 under-relaxes the update (x += omega H^-1 f).
* `NumpyVBD`: the Gauss-Seidel VBD sweep colour by colour in vectorised numpy: what a student would
  write without Taichi. It reads the simulation's adjacency arrays once and then works only on numpy.
"""
import numpy as np

from solver._ti import ti

from solver.vbd.layout import X
from solver.vbd.vertex_solve import force_hessian, newton_step


@ti.kernel
def _jacobi_step(state: ti.types.ndarray(), mass: ti.types.ndarray(), color_order: ti.types.ndarray(),
                 offsets: ti.types.ndarray(), others: ti.types.ndarray(), adj_f: ti.types.ndarray(),
                 params: ti.types.ndarray(), dx: ti.types.ndarray(), omega: ti.f64, dtype: ti.template()):
    """All free vertices from the same old positions, then x += omega dx: no colouring."""
    for k in range(color_order.shape[0]):
        f, H = force_hessian(state, mass, color_order, offsets, others, adj_f, params, k, dtype)
        dx[k] = newton_step(f, H, dtype)
    for k in range(color_order.shape[0]):
        state[X, color_order[k]] += ti.cast(omega, dtype) * dx[k]


class JacobiSweep:
    """Jacobi-ordered VBD on the arrays of `sim`: call `iterate(k)` between sim.begin_step/end_step."""

    def __init__(self, sim, omega: float = 1.0):
        self.sim = sim
        self.omega = float(omega)
        self.dx = ti.Vector.ndarray(3, sim.dtype, max(1, sim.topology.n_slots))

    def iterate(self, k: int = 1):
        a = self.sim.arrays
        for _ in range(k):
            _jacobi_step(a.state, a.mass, a.color_order, a.offsets, a.others, a.adj_f, a.params, self.dx,
                         self.omega, self.sim.dtype)


class NumpyVBD:
    """The VBD Gauss-Seidel sweep in vectorised numpy (float64), on the data of a `Simulation`.

    Usage: nv = NumpyVBD(sim); x = nv.sweep(x, y, k) runs k iterations from positions x (N, 3)
    toward the inertial target y (N, 3) with the simulation's h, mu, lam and masses.
    """

    def __init__(self, sim):
        self.h = float(sim.dt)
        self.mu, self.lam = float(sim.material.mu), float(sim.material.lam)
        self.alpha = 1.0 + self.mu / self.lam
        top = sim.topology
        order, offsets, others = (top.color_order.astype(np.int64), top.offsets.astype(np.int64),
                                  top.others.astype(np.int64))
        q, c, m_sq, vol = top.q, top.c, top.m_sq, top.volume
        mass = sim.masses
        self.colors = []
        for start, end in top.color_ranges:
            e0, e1 = offsets[start], offsets[end]
            verts = order[start:end]
            degree = np.diff(offsets[start:end + 1])
            self.colors.append(dict(
                verts=verts, owner=np.repeat(verts, degree), seg=offsets[start:end] - e0,
                others=others[e0:e1], q=q[e0:e1], c=c[e0:e1], m_sq=m_sq[e0:e1], vol=vol[e0:e1],
                m_h2=mass[verts] / self.h ** 2))

    def _solve_color(self, x, y, col):
        mu, lam, alpha = self.mu, self.lam, self.alpha
        xi = x[col["owner"]]                                       # (E, 3)
        d = x[col["others"]] - xi[:, None, :]                      # (E, 3, 3): d_j = x_j - x_i
        n = np.cross(d[:, 1] - d[:, 0], d[:, 2] - d[:, 0])         # area normal opposite i
        Fm = np.einsum("ej,eja->ea", col["q"], d)
        J = col["c"] * np.einsum("ea,ea->e", d[:, 0], n)
        w = -col["c"][:, None] * n
        vol = col["vol"]
        f_e = -vol[:, None] * (mu * Fm + (lam * (J - alpha))[:, None] * w)
        H_e = (vol * lam)[:, None, None] * w[:, :, None] * w[:, None, :]
        H_e[:, [0, 1, 2], [0, 1, 2]] += (vol * mu * col["m_sq"])[:, None]
        f = np.add.reduceat(f_e, col["seg"], axis=0)
        H = np.add.reduceat(H_e, col["seg"], axis=0)
        v = col["verts"]
        m_h2 = col["m_h2"]
        f += m_h2[:, None] * (y[v] - x[v])
        H[:, [0, 1, 2], [0, 1, 2]] += m_h2[:, None]
        x[v] += np.linalg.solve(H, f[:, :, None])[:, :, 0]

    def sweep(self, x, y, k: int = 1):
        x = np.array(x, dtype=np.float64)
        for _ in range(k):
            for col in self.colors:
                self._solve_color(x, y, col)
        return x
