"""Taichi helpers shared by the engine's kernel modules (the backend and the particle re-sort): a particle
matrix array's annotation, load and store in either layout (``MATRIX_STATE``), and a graph argument's
element type. Both modules import these from here, so neither imports the other at load time."""

import taichi as ti

mat3 = ti.math.mat3
ND = ti.types.ndarray


def matrix_nd(component_major: bool):
    """The kernels' annotation of a particle matrix array in either layout (``MATRIX_STATE``)."""
    return ND(ti.f32, 3) if component_major else ND(mat3, 2)


@ti.func
def load_mat3(A: ti.template(), b, p):
    """Particle ``p``'s matrix of run ``b`` from ``A`` in either layout (``MATRIX_STATE``)."""
    if ti.static(len(A.shape) == 3):   # component-major (B, 9, N)
        return ti.Matrix([[A[b, 0, p], A[b, 1, p], A[b, 2, p]], [A[b, 3, p], A[b, 4, p], A[b, 5, p]],
                          [A[b, 6, p], A[b, 7, p], A[b, 8, p]]])
    else:
        return A[b, p]


@ti.func
def store_mat3(A: ti.template(), b, p, M):
    """Write ``M`` as particle ``p``'s matrix of run ``b`` into ``A`` in either layout."""
    if ti.static(len(A.shape) == 3):
        for i, j in ti.static(ti.ndrange(3, 3)):
            A[b, 3 * i + j, p] = M[i, j]
    else:
        A[b, p] = M


def _element_type(arr):
    """A Taichi ndarray's element type as a graph argument takes it: a scalar, vector or matrix type."""
    if hasattr(arr, "m"):
        return ti.types.matrix(arr.n, arr.m, arr.dtype)
    if hasattr(arr, "n"):
        return ti.types.vector(arr.n, arr.dtype)
    return arr.dtype


__all__ = ["_element_type", "load_mat3", "matrix_nd", "store_mat3"]
