"""The frozen mass-spring model of a soft object: lumped masses, edge springs, volume term, dampers.

``build_body(mesh, material)`` turns a tet mesh and a material into a :class:`Body`; forces on a
body are computed by the compiled kernels of :mod:`softgrasp.physics.springs`,
:mod:`softgrasp.physics.volume` and :mod:`softgrasp.physics.forces_compiled` and collected per scene by
:mod:`softgrasp.sim.scene`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp import backend
from softgrasp.errors import ConfigError, MaterialError
from softgrasp.model.material import Material
from softgrasp.model.mesh.tetmesh import TetMesh
from softgrasp.model.network import NetworkCalibration, calibrate_network
from softgrasp.model.ranges import VOLUME_TERMS
from softgrasp.physics.forces import BlockPattern

if TYPE_CHECKING:  # loaded with the first nodal body: a plan of the per-tet term never needs it
    from softgrasp.physics.nodal_volume import NodalVolume

__all__ = ["Body", "build_body", "STANDARD_GRAVITY", "DEFAULT_DAMPING_RATIO"]

#: Standard gravity [m/s^2].
STANDARD_GRAVITY = 9.80665
#: Residual directional stiffness spread above which build_body warns.
ANISOTROPY_WARNING = 0.02
#: Default damping ratio of the body's fundamental mode (edge dashpots, stiffness-proportional).
DEFAULT_DAMPING_RATIO = 0.1
#: Up to this many nodes Newton factorises the nodal volume term's exact matrix; above, the
#: per-tet term's, with GMRES on the exact product (:meth:`Body.newton_jacobian`), unless the
#: solver cache asks for the exact one (the material tests do). Default plans
#: of the sphere measured both ways: exact 0.47, 0.76, 1.23 and 3.40 s at 388, 745, 1 239 and
#: 2 196 nodes; GMRES 0.75, 3.15, 2.14 and 2.81 s.
NODAL_DIRECT_MAX_NODES = 1500


def _row_max(J: sp.spmatrix) -> NDArray[np.float64]:
    """Per node, the largest absolute row sum of a (3N, 3N) matrix over the node's 3 rows, (N,)."""
    return np.asarray(abs(J).sum(axis=1)).ravel().reshape(-1, 3).max(axis=1)


@dataclass(frozen=True, eq=False)
class Body:
    """A calibrated non-linear mass-spring body (static model; positions live in the state).

    Attributes
    ----------
    mesh: the rest configuration.
    material: elastic constants, density, stress-strain law.
    mass: lumped node masses [kg], (N,); ``m_i = rho sum_{t ∋ i} V_t / 4``.
    stiffness: spring constants [N/m], (E,), on ``mesh.edges``.
    rest_length: spring rest lengths [m], (E,).
    kappa: volume-term modulus [Pa] (Lame lambda - mu).
    damping: edge dashpot constants [N s/m], (E,).
    damping_time: stiffness-proportional damping time beta [s] with ``damping = beta * stiffness``.
    gravity: acceleration of gravity [m/s^2], (3,).
    calibration: how springs and volume term were set (see :mod:`softgrasp.model.network`).
    volume: how the volume term counts volume: ``"element"`` per tet
        (:mod:`softgrasp.physics.volume`), ``"nodal"`` per node, on a quarter of each of its tets
        (:mod:`softgrasp.physics.nodal_volume`: no volumetric locking as nu nears 1/2).
    """

    mesh: TetMesh
    material: Material
    mass: NDArray[np.float64]
    stiffness: NDArray[np.float64]
    rest_length: NDArray[np.float64]
    kappa: float
    damping: NDArray[np.float64]
    damping_time: float
    gravity: NDArray[np.float64]
    calibration: NetworkCalibration
    volume: str = "element"

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return self.mesh.n_nodes

    @property
    def edges(self) -> NDArray[np.int64]:
        """Spring node pairs, (E, 2)."""
        return self.mesh.edges

    @property
    def total_mass(self) -> float:
        """Total mass [kg]."""
        return float(self.mass.sum())

    @property
    def density(self) -> float:
        """Mean density [kg/m^3]: total mass over the mesh's volume."""
        return self.total_mass / self.mesh.volume

    @property
    def barrier(self) -> bool:
        """Whether the volume term uses the inversion barrier (kappa >= 0)."""
        return self.kappa >= 0

    @property
    def _element_kappa(self) -> float:
        """kappa of the per-tet volume term the compiled force kernels add (0 for a nodal one)."""
        return self.kappa if self.volume == "element" else 0.0

    @cached_property
    def _nodal(self) -> NodalVolume | None:
        """The node-averaged volume term (:mod:`softgrasp.physics.nodal_volume`), or None."""
        if self.volume != "nodal" or self.kappa == 0.0:
            return None
        from softgrasp.physics.nodal_volume import NodalVolume

        return NodalVolume(self.mesh.tets, self.mesh.volumes, self.n_nodes, self.kappa, self.barrier)

    def placed_at(self, points: NDArray[np.float64]) -> Body:
        """This body with its rest shape at ``points`` [m], (N, 3), a rigid motion of its mesh
        (:meth:`~softgrasp.model.mesh.tetmesh.TetMesh.moved`): the object placed elsewhere, its
        springs, volume term and masses the same; itself when ``points`` are its mesh's."""
        pts = np.asarray(points, dtype=np.float64)
        if np.array_equal(pts, self.mesh.points):
            return self
        return replace(self, mesh=self.mesh.moved(pts))

    @property
    def weight(self) -> NDArray[np.float64]:
        """Total gravity force [N], (3,)."""
        return self.total_mass * self.gravity

    def internal_forces(
        self, x: NDArray[np.float64], v: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64]:
        """Spring + volume (+ edge damping if ``v`` is given) forces on the nodes [N], (N, 3)
        (:func:`softgrasp.physics.forces_compiled.internal_forces`). A body of at least
        :data:`~softgrasp.physics.forces_compiled.PARTITIONED_MIN_NODES` nodes sums them in the
        assembly's order on the calling thread's Numba threads (the static solver gives it the
        idle cores), the same to the bit on any number."""
        from softgrasp.physics import forces_compiled as elastic

        damped = v is not None and self.damping_time > 0
        forces = self._partitioned(x, v if damped else None, False)
        if forces is not None:
            out = forces[0]
        else:
            out = elastic.internal_forces(
                x,
                v if damped else None,
                self.edges,
                self.rest_length,
                self.stiffness,
                self.damping if damped else None,
                self.material.law,
                self.mesh.tets,
                self.mesh.volumes,
                self._element_kappa,
                self.barrier,
            )
        if self._nodal is not None:
            self._nodal.forces(x, out)
        return out

    def internal_energy(self, x: NDArray[np.float64]) -> float:
        """Elastic energy of springs and volume term [J], summed as :meth:`internal_forces`."""
        from softgrasp.physics import forces_compiled as elastic

        summed = self._partitioned(x, None, True)
        if summed is not None:
            energy = summed[1]
        else:
            energy = elastic.internal_energy(
                x,
                self.edges,
                self.rest_length,
                self.stiffness,
                self.material.law,
                self.mesh.tets,
                self.mesh.volumes,
                self._element_kappa,
                self.barrier,
            )
        if self._nodal is not None:
            energy += self._nodal.forces(x, np.zeros((self.n_nodes, 3)))
        return energy

    @cached_property
    def _jacobian_pattern(self) -> BlockPattern:
        """Sparsity of :meth:`internal_jacobian`, built once: the spring blocks, then the volume
        term's."""
        from softgrasp.physics.nodal_volume import star_pairs
        from softgrasp.physics.springs import spring_pairs
        from softgrasp.physics.volume import volume_pairs

        rows, cols = spring_pairs(self.edges)
        if self.kappa != 0.0:
            if self.volume == "element":
                vr, vc = volume_pairs(self.mesh.tets)
            else:
                vr, vc = star_pairs(self.mesh.tets, self.n_nodes)
            rows, cols = np.concatenate([rows, vr]), np.concatenate([cols, vc])
        return BlockPattern(self.n_nodes, rows, cols)

    @cached_property
    def _assembly_partition(self) -> tuple:
        """The elements in the compiled assembly's order
        (:func:`softgrasp.physics.forces_compiled.assembly_partition`)."""
        from softgrasp.physics import forces_compiled as elastic

        return elastic.assembly_partition(self.edges, self.mesh.tets, self.n_nodes)

    def _partitioned(
        self, x: NDArray[np.float64], v: NDArray[np.float64] | None, want_energy: bool
    ) -> tuple[NDArray[np.float64], float] | None:
        """(forces, energy) summed in the assembly's order on Numba's threads
        (:func:`softgrasp.physics.forces_compiled.partitioned_forces`) for a large body's polynomial law;
        None otherwise, and in a process forked from one whose Numba threads did not survive the
        fork (:func:`softgrasp.backend.forked`): the single-pass kernels then."""
        from softgrasp.physics import forces_compiled as elastic

        if self.n_nodes < elastic.PARTITIONED_MIN_NODES or backend.forked():
            return None
        return elastic.partitioned_forces(
            x, v, self._force_elements, self.material.law, self._element_kappa, self.barrier, want_energy
        )

    @cached_property
    def _force_elements(self) -> tuple:
        """The force kernels' per-element arrays in the assembly's order, for a large body
        (:func:`softgrasp.physics.forces_compiled.partitioned_elements`)."""
        from softgrasp.physics import forces_compiled as elastic

        return elastic.partitioned_elements(
            self.edges, self.rest_length, self.stiffness, self.damping, self.mesh.tets, self.mesh.volumes,
            self._assembly_partition,
        )  # fmt: skip

    def internal_jacobian(self, x: NDArray[np.float64], threads: int = 1) -> sp.csr_matrix:
        """``d f_internal / d x`` (negative stiffness), sparse (3N, 3N), assembled into the body's
        fixed sparsity pattern (the compiled kernels sum their blocks straight into its CSR data,
        on up to ``threads`` threads: the same sums on any number)."""
        from softgrasp.physics import forces_compiled as elastic

        pattern = self._jacobian_pattern
        data = elastic.internal_jacobian_data(
            x,
            self.edges,
            self.rest_length,
            self.stiffness,
            self.material.law,
            self.mesh.tets,
            self.mesh.volumes,
            self._element_kappa,
            self.barrier,
            pattern.block_base,
            pattern.block_stride,
            pattern.nnz,
            self._assembly_partition,
            threads,
        )
        if self._nodal is not None:
            self._nodal.add_jacobian(x, pattern.indptr, pattern.indices, data)
        return pattern.matrix(data)

    @cached_property
    def _element_twin(self) -> Body:
        """This body with the per-tet volume term (the same arrays)."""
        return replace(self, volume="element")

    def approximates(self, exact: bool = False) -> bool:
        """Whether :meth:`newton_jacobian` approximates ``d f / d x``: a nodal body above
        :data:`NODAL_DIRECT_MAX_NODES` nodes, unless ``exact`` asks for the exact matrix."""
        return self._nodal is not None and self.n_nodes > NODAL_DIRECT_MAX_NODES and not exact

    def newton_jacobian(self, x: NDArray[np.float64], threads: int = 1, exact: bool = False) -> sp.csr_matrix:
        """The matrix Newton factorises: ``d f / d x``, or above :data:`NODAL_DIRECT_MAX_NODES`
        (unless ``exact``) an approximation of it in the per-tet term's sparsity: the nodal
        volume term's (whose exact matrix has about four times the blocks, and costs four to six
        times as much to factorise) by the per-tet term's, stiffer (it locks) but alike at every
        uniform deformation, which preconditions GMRES on the exact product (about 12 iterations
        at nu = 0.45 on a plan); :meth:`newton_correction` turns its products into the exact
        ones."""
        if not self.approximates(exact):
            return self.internal_jacobian(x, threads)
        return self._element_twin.internal_jacobian(x, threads)

    def newton_correction(
        self, x: NDArray[np.float64], exact: bool = False
    ) -> Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]] | None:
        """What turns a product with ``-newton_jacobian(x, exact=exact)`` into one with
        ``-internal_jacobian(x)``: a function adding ``(J_approx - J) v`` to ``out`` (flat, 3N,
        contiguous: changed in place), or None where they are one matrix."""
        if not self.approximates(exact):
            return None
        nodal, shape = self._nodal, (self.n_nodes, 3)

        def add(v: NDArray[np.float64], out: NDArray[np.float64]) -> NDArray[np.float64]:
            nodal.add_difference(x, v.reshape(shape), out.reshape(shape))
            return out

        return add

    def damping_jacobian(self, x: NDArray[np.float64]) -> sp.csr_matrix:
        """``d f_damping / d v``, sparse (3N, 3N)."""
        from softgrasp.physics.springs import edge_damping_jacobian

        return edge_damping_jacobian(x, self.edges, self.damping)

    @cached_property
    def rest_jacobian(self) -> sp.csr_matrix:
        """Internal Jacobian at the rest configuration."""
        return self.internal_jacobian(np.asarray(self.mesh.points))

    @cached_property
    def node_stiffness(self) -> NDArray[np.float64]:
        """Per-node stiffness scale [N/m], (N,): half the largest absolute row sum of the node's rest
        stiffness rows (the sum of the stiffnesses attaching it, for springs).

        Used to size penalty contacts and time steps.
        """
        return self._stiffness_rows / 2.0  # diagonal + off-diagonal row sums: twice the spring sum

    @cached_property
    def node_edge_length(self) -> NDArray[np.float64]:
        """Per node, the mean rest length of its edges [m], (N,), read-only: the mesh's local size."""
        e = self.mesh.edges
        total = np.bincount(e.ravel(), weights=np.repeat(self.rest_length, 2), minlength=self.n_nodes)
        count = np.bincount(e.ravel(), minlength=self.n_nodes)
        out = total / np.maximum(count, 1)
        out.setflags(write=False)
        return out

    @cached_property
    def _stiffness_rows(self) -> NDArray[np.float64]:
        """Per node, the largest absolute row sum over its 3 rows of the rest stiffness matrix
        [N/m], (N,), read-only."""
        k = _row_max(self.rest_jacobian)
        k.setflags(write=False)
        return k

    @cached_property
    def rest_row_sums(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Per node, the largest absolute row sum over its 3 rows of the rest stiffness matrix
        [N/m] (twice :attr:`node_stiffness`) and of the rest damping matrix [N s/m] (zeros without
        dashpots), (N,) each, read-only: the Gershgorin bounds of
        :func:`softgrasp.sim.stability.node_gershgorin`, computed once (the damping matrix's
        assembly costs ~14 ms at 2 196 nodes, and every simulation asks)."""
        if self.damping_time > 0:
            c = _row_max(self.damping_jacobian(np.asarray(self.mesh.points)))
        else:
            c = np.zeros(self.n_nodes)
        c.setflags(write=False)
        return self._stiffness_rows, c

    @cached_property
    def fundamental_frequency(self) -> float:
        """Estimate of the lowest elastic angular frequency [rad/s]: pi c / L with the bar-wave
        speed c = sqrt(E / rho) and L the largest extent of the mesh."""
        rho = self.density
        L = float(np.ptp(self.mesh.points, axis=0).max())
        return math.pi * math.sqrt(self.material.E / rho) / L

    def describe(self) -> dict[str, object]:
        """JSON-ready summary of the model."""
        return {
            "nodes": self.mesh.n_nodes,
            "tets": self.mesh.n_tets,
            "edges": int(len(self.edges)),
            "facets": int(len(self.mesh.facets)),
            "volume_m3": self.mesh.volume,
            "mass_kg": self.total_mass,
            "material": self.material.describe(),
            "damping_time_s": self.damping_time,
            "gravity_m_s2": self.gravity.tolist(),
            "network": self.calibration.describe(),
            "volume_term": self.volume,
        }


def build_body(
    mesh: TetMesh,
    material: Material,
    *,
    mass: float | None = None,
    damping_ratio: float = DEFAULT_DAMPING_RATIO,
    gravity: float = STANDARD_GRAVITY,
    isotropize: bool = True,
    volume: str = "element",
) -> Body:
    """Build the mass-spring model of ``mesh`` made of ``material``.

    Parameters
    ----------
    mesh:
        Rest configuration.
    material:
        Elastic constants and law; its density is used unless ``mass`` is given.
    mass:
        Total mass [kg]; overrides the material density (density = mass / volume).
    damping_ratio:
        Damping ratio of the fundamental mode (>= 0); edge dashpots ``c_e = beta k_e`` with
        ``beta = 2 zeta / omega_1``. 0 gives an undamped body.
    gravity:
        Magnitude [m/s^2] of gravity, acting along -z. 0 switches it off.
    isotropize:
        Direction re-weighting of the springs (see :func:`softgrasp.model.network.calibrate_network`).
    volume:
        ``"element"`` (a volume term per tet) or ``"nodal"`` (per node: for nu near 1/2, where
        the per-tet term locks; :mod:`softgrasp.physics.nodal_volume`).

    Raises
    ------
    MaterialError
        No density and no mass, or a non-positive mass, damping ratio or gravity.
    ConfigError
        ``volume`` is neither ``"element"`` nor ``"nodal"``.
    """
    if volume not in VOLUME_TERMS:
        raise ConfigError(f"volume term {volume!r} is unknown; choose one of {', '.join(VOLUME_TERMS)}")
    if mass is not None:
        if not (math.isfinite(mass) and mass > 0):
            raise MaterialError(f"object mass = {mass} kg is invalid: it must be > 0")
        rho = mass / mesh.volume
    elif material.density is not None:
        rho = material.density
    else:
        raise MaterialError("material has no density; give the object's mass or a density")
    if not (math.isfinite(damping_ratio) and damping_ratio >= 0):
        raise MaterialError(f"damping ratio = {damping_ratio} is invalid: it must be >= 0")
    if not (math.isfinite(gravity) and gravity >= 0):
        raise MaterialError(f"gravity = {gravity} m/s^2 is invalid: it must be >= 0")
    node_mass = np.zeros(mesh.n_nodes)
    np.add.at(node_mass, mesh.tets.ravel(), np.repeat(rho * mesh.volumes / 4.0, 4))
    cal = calibrate_network(mesh, material.E, material.nu, isotropize=isotropize)
    if isotropize and cal.anisotropy_after > ANISOTROPY_WARNING:
        warnings.warn(
            f"the springs of mesh '{mesh.name}' cannot be made isotropic (directional stiffness "
            f"spread {cal.anisotropy_after:.0%} after re-weighting); stiffness will depend on the "
            "loading direction. Use cells closer to cubes (box) or an unstructured mesh.",
            stacklevel=2,
        )
    L = float(np.ptp(mesh.points, axis=0).max())
    omega1 = math.pi * math.sqrt(material.E / rho) / L
    beta = 2.0 * damping_ratio / omega1
    mat = material if material.density == rho else material.with_density(rho)
    return Body(
        mesh=mesh,
        material=mat,
        mass=node_mass,
        stiffness=cal.stiffness,
        rest_length=np.asarray(mesh.edge_lengths),
        kappa=cal.kappa,
        damping=beta * cal.stiffness,
        damping_time=beta,
        gravity=np.array([0.0, 0.0, -gravity]),
        calibration=cal,
        volume=volume,
    )
