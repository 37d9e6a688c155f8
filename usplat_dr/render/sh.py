"""Spherical-harmonics colour of the 3DGS rasteriser, degrees 0..3, on Dr.Jit arrays.

The basis constants are those of the 3DGS CUDA code (``auxiliary.h``). Works on any Dr.Jit
backend; differentiated by Dr.Jit AD.
"""

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_degree_for(num_coeffs: int) -> int:
    """Degree d with (d + 1)^2 == ``num_coeffs`` (1, 4, 9, 16 or 25), or ``ValueError``."""
    for degree in range(5):
        if (degree + 1) ** 2 == num_coeffs:
            return degree
    raise ValueError(
        f"sh_coefficients must have (degree+1)^2 coefficients with degree 0..4 "
        f"(1, 4, 9, 16 or 25), got {num_coeffs}"
    )


def _standard_basis(x, y, z, degree: int) -> list:
    """The 3DGS basis functions 0..(degree+1)^2-1 at the unit direction (x, y, z)."""
    basis = [C0]
    if degree >= 1:
        basis += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        basis += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z,
                  C2[4] * (xx - yy)]
    if degree >= 3:
        basis += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                  C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
                  C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    return basis


def sh_basis(x, y, z, degree: int, basis: str = "3dgs") -> list:
    """Basis values at a unit direction, as a list of (degree+1)^2 Dr.Jit arrays or floats.

    Parameter ``x, y, z`` (``Float``, one lane per Gaussian): unit view direction in world space.
    Parameter ``degree`` (``int``, 0..3): highest degree evaluated.
    Parameter ``basis`` (``str``): ``"3dgs"`` or ``"mvsplat"`` (see ``RasterSettings``).
    """
    if basis == "3dgs":
        return _standard_basis(x, y, z, degree)
    # diff-gaussian-rasterization-modified: the standard basis at (z, x, y) ...
    values = _standard_basis(z, x, y, degree)
    if degree >= 3:
        # ... except that its forward pass evaluates coefficient 14 as z (z^2 - x^2) where the
        # permuted basis gives y (z^2 - x^2) (docs/mvsplat_notes.md sec. 3, fixture `sh_basis`).
        values[14] = C3[5] * z * (z * z - x * x)
    return values


def eval_sh_color(coeffs: list, x, y, z, degree: int, basis: str = "3dgs") -> list:
    """RGB colour ``max(sum_i basis_i * coeffs[c][i] + 0.5, 0)`` of each Gaussian.

    Parameter ``coeffs`` (``list[list[Float]]``, ``coeffs[c][i]`` one lane per Gaussian): the
    coefficients of colour channel c, at least (degree+1)^2 of them; higher ones are ignored, as
    the reference ignores degree 4.
    Returns ``[r, g, b]`` (``Float``).
    """
    import drjit as dr  # here only: sh_basis also serves NumPy and torch without Dr.Jit

    values = sh_basis(x, y, z, degree, basis)
    colors = []
    for channel in coeffs:
        acc = channel[0] * values[0]
        for i in range(1, len(values)):
            acc = dr.fma(channel[i], values[i], acc)
        colors.append(dr.maximum(acc + 0.5, 0.0))
    return colors
