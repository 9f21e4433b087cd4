#!/usr/bin/env python3
"""Independent finite-element reference for cutsim's branched grid (scikit-fem).

Reads the reference problems that `accuracy-speed export-problems DIR` writes (the
level-0 voxel mesh of each problem: nodes, hexahedra, materials, fixed nodes, the load,
the sample points) and solves linear elasticity on the same mesh with scikit-fem:

- hex1: trilinear hexahedra (ElementHex1), fully integrated, always;
- hex1p0: trilinear hexahedra with one constant pressure per hexahedron (the mixed
  Hex1–Hex0 pair with the pressure eliminated: the mean-dilatation or B-bar element),
  always;
- hex2: triquadratic hexahedra (ElementHex2) for the small bodies;
- mixed: Taylor–Hood hexahedra (ElementHex2 displacement, ElementHex1 pressure, the
  saddle-point system solved as it is), which do not lock as ν → 0.5, where asked;

and the lowest eigenfrequency (consistent mass) where asked. Writes one JSON result per
problem: the displacement at every sample point.

    python solve.py PROBLEM_DIR RESULT_DIR [NAME ...]

Nothing here shares code with the Rust side: the stiffness, the loads (body force and
surface traction integrated by scikit-fem's quadrature) and the solve are scikit-fem's
and SciPy's.
"""

import json
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import scipy
import scipy.sparse.linalg as spla
import skfem
import scipy.sparse as sp
from skfem import Basis, BilinearForm, ElementHex0, ElementHex1, ElementHex2, ElementVector, FacetBasis, LinearForm, MeshHex, asm
from skfem.helpers import ddot, div, dot, eye, sym_grad, trace

# Our corner n sits at (n & 1, n >> 1 & 1, n >> 2 & 1); scikit-fem's hexahedron numbers
# its vertices (0,0,0), (0,0,1), (0,1,0), (1,0,0), (0,1,1), (1,0,1), (1,1,0), (1,1,1).
SKFEM_FROM_OURS = [0, 4, 2, 1, 6, 5, 3, 7]

# Problems with more unknowns than this are solved iteratively (the liver: ~135k).
DIRECT_LIMIT = 80_000


@BilinearForm
def stiffness(u, v, w):
    eps = sym_grad(u)
    sigma = 2.0 * w.mu * eps + eye(w.lam * trace(eps), 3)
    return ddot(sigma, sym_grad(v))


@BilinearForm
def mass(u, v, w):
    return w.rho * dot(u, v)


@BilinearForm
def divergence(u, q, w):
    return div(u) * q


@BilinearForm
def compliance(p, q, w):
    return p * q / w.kappa


def element_field(basis, values):
    """A per-element constant as a quadrature-point field."""
    return np.repeat(values[:, None], basis.X.shape[1], axis=1)


def fixed_dofs(basis, mesh, fixed_nodes):
    """Every degree of freedom on an entity whose vertices are all fixed."""
    is_fixed = np.zeros(mesh.p.shape[1], dtype=bool)
    is_fixed[fixed_nodes] = True
    dofs = [basis.nodal_dofs[:, is_fixed].ravel()]
    if basis.edge_dofs.size:
        held = np.all(is_fixed[mesh.edges], axis=0)
        dofs.append(basis.edge_dofs[:, held].ravel())
    if basis.facet_dofs.size:
        held = np.all(is_fixed[mesh.facets], axis=0)
        dofs.append(basis.facet_dofs[:, held].ravel())
    if basis.interior_dofs.size:
        held = np.all(is_fixed[mesh.t], axis=0)
        dofs.append(basis.interior_dofs[:, held].ravel())
    return np.unique(np.concatenate(dofs))


def solve_one(problem, mesh, element, pressure=None):
    """Displacements in `element`; with `pressure` (an element for it) the volumetric
    part is carried by that pressure field: eliminated where it is piecewise constant
    (Hex0: the mean-dilatation element), else solved together with the displacement."""
    started = time.perf_counter()
    basis = Basis(mesh, ElementVector(element()), intorder=4 if element is ElementHex2 else 2)
    materials = problem["materials"]
    material = np.asarray(problem["element_material"], dtype=np.int64)
    young = np.array([m["young_pa"] for m in materials])[material]
    poisson = np.array([m["poisson"] for m in materials])[material]
    density = np.array([m["density_kg_per_m3"] for m in materials])[material]
    lam = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    mu = young / (2.0 * (1.0 + poisson))
    kappa = lam + 2.0 * mu / 3.0
    if pressure is None:
        K = asm(stiffness, basis, lam=element_field(basis, lam), mu=element_field(basis, mu))
    else:
        # The deviatoric part (bulk modulus λ + 2μ/3 zero at every point) plus the pressure's.
        K = asm(stiffness, basis, lam=element_field(basis, -2.0 * mu / 3.0), mu=element_field(basis, mu))
        pressure_basis = basis.with_element(pressure())
        B = asm(divergence, basis, pressure_basis)
        C = asm(compliance, pressure_basis, kappa=element_field(pressure_basis, kappa))
    f = np.zeros(basis.N)
    if problem["gravity_m_per_s2"] is not None:
        g = problem["gravity_m_per_s2"]
        rho = element_field(basis, density)

        @LinearForm
        def body(v, w):
            return w.rho * (g[0] * v[0] + g[1] * v[1] + g[2] * v[2])

        f += asm(body, basis, rho=rho)
    if problem["traction"] is not None:
        traction = problem["traction"]
        axis, at, t = traction["axis"], traction["coordinate_m"], traction["traction_pa"]
        facets = mesh.facets_satisfying(lambda x: np.isclose(x[axis], at, rtol=0.0, atol=1e-9), boundaries_only=True)
        if len(facets) == 0:
            raise SystemExit(f"{problem['name']}: no boundary facet at coordinate {at} on axis {axis}")
        facet_basis = FacetBasis(mesh, ElementVector(element()), facets=facets, intorder=4)

        @LinearForm
        def surface(v, w):
            return t[0] * v[0] + t[1] * v[1] + t[2] * v[2]

        f += asm(surface, facet_basis)
    D = fixed_dofs(basis, mesh, np.asarray(problem["fixed"], dtype=np.int64))
    free = np.setdiff1d(np.arange(basis.N), D)
    if pressure is ElementHex0:
        # C is diagonal (a volume per hexahedron over κ): p = C⁻¹ B u, K += Bᵀ C⁻¹ B.
        K = K + B.T @ sp.diags(1.0 / C.diagonal()) @ B
    K_ff = K[free][:, free].tocsc()
    u = np.zeros(basis.N)
    factor = None
    if pressure is not None and pressure is not ElementHex0:
        # [K_dev Bᵀ; B −C] [u; p] = [f; 0]: symmetric, indefinite, solved directly.
        B_f = B[:, free]
        system = sp.bmat([[K_ff, B_f.T], [B_f, -C]], format="csc")
        rhs = np.concatenate([f[free], np.zeros(pressure_basis.N)])
        solution = spla.splu(system).solve(rhs)
        u[free] = solution[: len(free)]
        residual = np.linalg.norm(system @ solution - rhs) / np.linalg.norm(rhs)
        how = "direct (SuperLU), saddle point"
    elif len(free) <= DIRECT_LIMIT:
        # SuperLU's default ordering (COLAMD): minimum degree on AᵀA + A took 9 times longer.
        factor = spla.splu(K_ff)
        u[free] = factor.solve(f[free])
        how = "direct (SuperLU)"
    else:
        diagonal = K_ff.diagonal()
        preconditioner = spla.LinearOperator(K_ff.shape, matvec=lambda r: r / diagonal)
        x, info = spla.cg(K_ff, f[free], rtol=1e-12, atol=0.0, maxiter=200_000, M=preconditioner)
        if info != 0:
            raise SystemExit(f"{problem['name']}: conjugate gradient did not converge (info {info})")
        u[free] = x
        how = "conjugate gradient (Jacobi), relative residual 1e-12"
    if pressure is None or pressure is ElementHex0:
        residual = np.linalg.norm(K_ff @ u[free] - f[free]) / np.linalg.norm(f[free])
    sample_nodes = np.asarray(problem["sample_nodes"], dtype=np.int64)
    displacement = u[basis.nodal_dofs[:, sample_nodes]].T
    out = {
        "displacement_m": displacement.tolist(),
        "dofs": int(len(free)),
        "solver": how,
        "relative_residual": float(residual),
    }
    if problem["frequency"] and (pressure is None or pressure is ElementHex0):
        M = asm(mass, basis, rho=element_field(basis, density))
        M_ff = M[free][:, free].tocsc()
        inverse = spla.LinearOperator(K_ff.shape, matvec=factor.solve) if factor is not None else None
        values = spla.eigsh(K_ff, k=3, M=M_ff, sigma=0.0, which="LM", OPinv=inverse, return_eigenvectors=False)
        out["first_frequency_hz"] = float(np.sqrt(np.min(values)) / (2.0 * np.pi))
    out["seconds"] = time.perf_counter() - started
    return out


def solve_problem(path, result_dir):
    """Solves the problem at `path`, writes its result into `result_dir` and returns the
    lines that tell what was solved (printed by the parent, one problem at a time)."""
    problem = json.loads(path.read_text())
    nodes = np.asarray(problem["nodes"], dtype=np.float64).T
    hexes = np.asarray(problem["hexes"], dtype=np.int64)[:, SKFEM_FROM_OURS].T
    mesh = MeshHex(np.ascontiguousarray(nodes), np.ascontiguousarray(hexes))
    result = {
        "problem": problem["name"],
        "summary": problem["summary"],
        "digest": problem["digest"],
        "generator": f"tools/reference/solve.py with scikit-fem {skfem.__version__}, NumPy {np.__version__}, SciPy {scipy.__version__}",
        "mesh": {"nodes": int(nodes.shape[1]), "hexahedra": int(hexes.shape[1])},
        "samples": problem["samples"],
    }
    lines = [f"{problem['name']}: {hexes.shape[1]} hexahedra"]
    result["hex1"] = solve_one(problem, mesh, ElementHex1)
    lines.append(f"  Hex1: {result['hex1']['dofs']} unknowns, {result['hex1']['seconds']:.1f} s")
    result["hex1p0"] = solve_one(problem, mesh, ElementHex1, pressure=ElementHex0)
    lines.append(f"  Hex1 with a constant pressure per hexahedron: {result['hex1p0']['seconds']:.1f} s")
    if problem.get("mixed"):
        result["mixed"] = solve_one(problem, mesh, ElementHex2, pressure=ElementHex1)
        lines.append(f"  Taylor–Hood (Hex2–Hex1): {result['mixed']['dofs']} unknowns, {result['mixed']['seconds']:.1f} s")
    if problem["quadratic"]:
        result["hex2"] = solve_one(problem, mesh, ElementHex2)
        lines.append(f"  Hex2: {result['hex2']['dofs']} unknowns, {result['hex2']['seconds']:.1f} s")
    out = result_dir / f"{problem['name']}.json"
    out.write_text(json.dumps(result, indent=1) + "\n")
    lines.append(f"  wrote {out}")
    return "\n".join(lines)


def estimated_cost(problem):
    """The relative time a problem takes, from its hexahedra and the elements it is
    solved with (measured on the bundled problems: the liver's 38,634 hexahedra in Hex1
    and Hex1–P0 take twice as long as a cantilever's 2,048 in Hex2, Taylor–Hood a third
    longer than Hex2)."""
    per_hexahedron = 36 if problem.get("mixed") else 27 if problem["quadratic"] else 3
    return len(problem["hexes"]) * per_hexahedron


def main():
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    problem_dir, result_dir = Path(sys.argv[1]), Path(sys.argv[2])
    names = sys.argv[3:]
    result_dir.mkdir(parents=True, exist_ok=True)
    paths = sorted(problem_dir.glob("*.json"))
    if names:
        paths = [p for p in paths if p.stem in names]
    if not paths:
        raise SystemExit(f"no problems in {problem_dir} (make them with: cargo run -p cutsim-sim --bin accuracy-speed -- export-problems {problem_dir})")
    # The problems are independent and each solve is single-threaded (SuperLU, SciPy's
    # sparse products): one process per core, the costliest problems first so that the
    # small ones fill in at the end. On the 2-core CI machine this takes about 4 of the 8
    # minutes that solving them one after another took.
    paths.sort(key=lambda p: estimated_cost(json.loads(p.read_text())), reverse=True)
    jobs = int(os.environ.get("CUTSIM_REFERENCE_JOBS") or os.cpu_count() or 1)
    workers = max(1, min(len(paths), jobs))
    print(f"solving {len(paths)} problems in {workers} processes ...", flush=True)
    if workers == 1:
        for path in paths:
            print(solve_problem(path, result_dir), flush=True)
        return
    # One BLAS thread per process (the children read it when they import NumPy).
    for variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(variable, "1")
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        solving = [pool.submit(solve_problem, path, result_dir) for path in paths]
        for job in as_completed(solving):
            print(job.result(), flush=True)


if __name__ == "__main__":
    main()
