"""Sparse Cholesky (CHOLMOD) inside `jit`, through the optional `sparsax` package."""

import ctypes
import importlib.metadata
import importlib.util
import os
import sys
import warnings
from types import ModuleType
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float

from ...factors import GroupLayout
from .._linearization import flatten_layout, unflatten_layout
from ._linear_solver import (
    AbstractFactorization,
    AbstractNormalSolver,
    normal_operator_of,
)
from ._sparse import assemble_sparse, SparsityPattern


def sparsax_available() -> bool:
    """Whether `sparsax` is importable and JAX runs in 64-bit mode (it needs both)."""
    return (
        importlib.util.find_spec("sparsax") is not None
        and jax.config.read("jax_enable_x64")  # pyright: ignore[reportAttributeAccessIssue]
    )


_MKL_SEQUENTIAL = 1  # MKL_THREADING_SEQUENTIAL in mkl_service.h


def _mkl_runtime() -> str | None:
    """Path of MKL's single dynamic library, if the `mkl` wheel is installed."""
    try:
        files = importlib.metadata.files("mkl") or []
    except importlib.metadata.PackageNotFoundError:
        return None
    for f in files:
        if f.name.startswith("libmkl_rt.so"):
            path = str(f.locate())
            if os.path.exists(path):
                return path
    return None


class _Blas:
    """Which BLAS CHOLMOD (inside sparsax) was bound to in this process: a fact
    fixed when sparsax's extension is first loaded, not a setting."""

    name: Literal["mkl", "bundled"] | None = None


def _import_sparsax() -> ModuleType:
    """Import sparsax, first making MKL's BLAS the one CHOLMOD binds to, if the
    `mkl` wheel is installed (the `sparse` extra installs it on Linux x86-64).

    sparsax's wheel bundles a generic ATLAS, and its CHOLMOD resolves the BLAS
    symbols (`dgemm_`, `dsyrk_`, `dtrsm_`, `dpotrf_`) when the extension
    loads. A library loaded before it with `RTLD_GLOBAL` comes first in that
    lookup, so loading MKL's runtime library that way makes the supernodal
    factorisation run MKL's kernels (faster than the bundled ATLAS; the
    performance page has the figures). Python extensions never share BLAS
    symbols otherwise (NumPy's and SciPy's OpenBLAS are prefixed), so nothing
    else changes. MKL runs sequentially unless `MKL_THREADING_LAYER` says
    otherwise: XLA already uses the cores.
    """
    if _Blas.name is None:
        if "sparsax_cpp" not in sys.modules:
            path = _mkl_runtime()
            if path is not None:
                try:
                    lib = ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)
                    if "MKL_THREADING_LAYER" not in os.environ:
                        lib.MKL_Set_Threading_Layer(ctypes.c_int(_MKL_SEQUENTIAL))
                    _Blas.name = "mkl"
                except (OSError, AttributeError) as e:
                    warnings.warn(
                        f"eqsmooth: could not load MKL from {path} ({e}); "
                        "SparsaxCholesky uses the BLAS bundled with sparsax",
                        RuntimeWarning,
                        stacklevel=2,
                    )
        if _Blas.name is None:
            _Blas.name = "bundled"
    import sparsax

    return sparsax


def sparsax_blas() -> Literal["mkl", "bundled"]:
    """The BLAS that [`eqsmooth.solve.SparsaxCholesky`][]'s CHOLMOD runs on.

    `"mkl"` when the `mkl` wheel was installed (`pip install
    "eqsmooth[sparse]"` installs it on Linux x86-64) and sparsax was first
    imported through eqsmooth; `"bundled"` for the generic ATLAS inside
    sparsax's wheel (no `mkl`, or sparsax imported before eqsmooth used it).
    Calling this imports sparsax, which binds the choice for the process.
    """
    _import_sparsax()
    assert _Blas.name is not None
    return _Blas.name


def _upper_coo(pattern: SparsityPattern) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns and stored-entry positions of the upper triangle, once per
    pattern (sparsax reads a symmetric matrix from its upper triangle)."""
    cached = pattern.cache.get("sparsax_upper")
    if cached is None:
        keep = np.nonzero(pattern.indices <= pattern.columns)[0]
        cached = (pattern.indices[keep], pattern.columns[keep], keep.astype(np.int32))
        pattern.cache["sparsax_upper"] = cached
    return cached


class SparsaxFactorization(AbstractFactorization):
    """The state of [`eqsmooth.solve.SparsaxCholesky`][]: the assembled normal matrix.

    CHOLMOD's factor lives inside sparsax (cached per sparsity pattern and
    values); `log_det` and `inverse_block_diagonal` ask it for the
    log-determinant and the selected inverse (Takahashi's recurrence: the
    entries of the inverse on the matrix's own pattern, which holds every
    diagonal block).
    """

    data: Float[Array, " nnz"]
    ok: Bool[Array, ""]
    pattern: SparsityPattern = eqx.field(static=True)
    layout: tuple[GroupLayout, ...] = eqx.field(static=True)

    def _upper(self):
        sparsax = _import_sparsax()
        rows, cols, keep = _upper_coo(self.pattern)
        return sparsax, rows, cols, self.data[keep].astype(jnp.float64)

    def solve(self, b: Float[Array, " N"]) -> Float[Array, " N"]:
        sparsax, rows, cols, values = self._upper()
        return sparsax.solve(rows, cols, values, b.astype(jnp.float64))

    def log_det(self) -> Float[Array, ""]:
        sparsax, rows, cols, values = self._upper()
        out = sparsax.logdet(rows, cols, values, self.pattern.size)
        return out.astype(self.data.dtype)

    def inverse_block_diagonal(self) -> dict[str, Float[Array, "_N _d _d"]]:
        sparsax, rows, cols, values = self._upper()
        z = sparsax.selinv(rows, cols, values, self.pattern.size)
        # Scatter the selected inverse into the diagonal blocks, mirrored.
        out, start = {}, 0
        for g in self.layout:
            size, d = g.count * g.dim, g.dim
            r, c = rows - start, cols - start
            inside = (r >= 0) & (r < size) & (c >= 0) & (c < size) & (r // d == c // d)
            idx = np.nonzero(inside)[0]
            k = r[idx] // d
            blocks = jnp.zeros((g.count, d, d), self.data.dtype)
            vals = z[idx].astype(self.data.dtype)
            blocks = blocks.at[k, r[idx] % d, c[idx] % d].set(vals)
            blocks = blocks.at[k, c[idx] % d, r[idx] % d].set(vals)
            out[g.name] = blocks
            start += size
        return out


class SparsaxCholesky(AbstractNormalSolver):
    """Sparse supernodal Cholesky (CHOLMOD) of `JᵀJ + diag(damping)` inside `jit`.

    A lineax solver of the [`eqsmooth.solve.NormalOperator`][] built on the
    optional [sparsax](https://pypi.org/project/sparsax/) package
    (`pip install "eqsmooth[sparse]"`: manylinux wheels with SuiteSparse
    bundled, no system packages), which runs CHOLMOD as an XLA FFI custom
    call: no Python callback, so it works inside `jit`, `vmap` and loops at
    native speed, its symbolic analysis (fill-reducing ordering) is cached per
    sparsity pattern, and programs using it can be stored in JAX's persistent
    compilation cache. The normal matrix is assembled as for
    [`eqsmooth.solve.SparseLU`][]. Its state is a
    [`eqsmooth.solve.SparsaxFactorization`][]: log-determinants and marginal
    covariances (selected inversion) of general sparse graphs.

    The supernodal factorisation spends its time in BLAS. sparsax's wheel
    bundles a generic ATLAS; with the `mkl` wheel installed (the `sparse`
    extra installs it on Linux x86-64) eqsmooth has CHOLMOD call MKL instead,
    which is faster (the performance page has the figures;
    [`eqsmooth.solve.sparsax_blas`][] says which one is in use).

    When sparsax is installed (and JAX runs in 64-bit mode), it is the default
    linear solver of graphs that are neither chains nor small (see
    [`eqsmooth.solve.default_linear_solver`][]).

    Limits: float64 only (float32 systems are solved in float64 and cast
    back, which needs `jax_enable_x64`); CPU only. A singular system whose
    rounding leaves every pivot positive gives a step that is not finite or
    not a solution, reported as `RESULTS.singular` with a zero step (a
    residual check); but a matrix that CHOLMOD finds not positive definite
    stops the program with sparsax's runtime error ("matrix is not positive
    definite"), which no result code can catch. Levenberg-Marquardt's damping
    keeps its systems positive definite; Gauss-Newton on a graph with an
    unfixed gauge freedom can hit this error, where
    [`eqsmooth.solve.SparseLU`][] returns `RESULTS.singular`.
    """

    def __check_init__(self):
        if importlib.util.find_spec("sparsax") is None:
            raise ImportError(
                "SparsaxCholesky needs sparsax: pip install 'eqsmooth[sparse]' (or "
                "pip install sparsax). Or use SparseLU() (SciPy only)."
            )

    def init(
        self, operator: lx.AbstractLinearOperator, options: dict[str, Any]
    ) -> SparsaxFactorization:
        del options
        op = normal_operator_of(operator, "SparsaxCholesky")
        if not jax.config.read("jax_enable_x64"):  # pyright: ignore[reportAttributeAccessIssue]
            raise ValueError(
                "SparsaxCholesky solves in float64: turn on "
                'jax.config.update("jax_enable_x64", True) first'
            )
        state = assemble_sparse(op)
        ok = jnp.all(jnp.isfinite(state.data))
        return SparsaxFactorization(state.data, ok, state.pattern, state.layout)

    def compute(self, state: SparsaxFactorization, vector, options: dict[str, Any]):
        del options
        b = flatten_layout(state.layout, vector)
        dtype = b.dtype
        # A non-finite matrix would make CHOLMOD fail (a runtime error): solve
        # the identity instead and report the failure.
        safe = eqx.tree_at(
            lambda s: s.data,
            state,
            jnp.where(state.ok, state.data, _identity_data(state.pattern, dtype)),
        )
        x = safe.solve(b).astype(dtype)
        # Backward-stable Cholesky leaves ‖Ax − b‖ at rounding level relative
        # to ‖A‖‖x‖; more (or a non-finite x) means the factorisation broke
        # down on a (numerically) singular matrix.
        r = _csc_matvec(state, x) - b
        scale = jnp.max(jnp.abs(state.data)) * jnp.max(jnp.abs(x)) + jnp.max(jnp.abs(b))
        tol = jnp.sqrt(jnp.asarray(np.finfo(np.dtype(dtype)).eps, dtype))
        ok = state.ok & jnp.all(jnp.isfinite(x)) & (jnp.max(jnp.abs(r)) <= tol * scale)
        x = jnp.where(ok, x, jnp.zeros_like(x))
        result = lx.RESULTS.where(ok, lx.RESULTS.successful, lx.RESULTS.singular)
        return unflatten_layout(state.layout, x), result, {}


def _identity_data(pattern: SparsityPattern, dtype) -> Array:
    return jnp.zeros((pattern.nnz,), dtype).at[pattern.diagonal].set(1)


def _csc_matvec(state: SparsaxFactorization, x: Array) -> Array:
    p = state.pattern
    return jax.ops.segment_sum(
        state.data.astype(x.dtype) * x[p.columns], p.indices, num_segments=p.size
    )
