"""Per-pixel alpha compositing with a hand-written backward (``dr.CustomOp``).

Forward (per pixel, front to back over its tile's depth-sorted list, as the 3DGS CUDA kernel):
``power = -0.5 (a dx^2 + c dy^2) - b dx dy`` with ``d = centre - pixel``; skipped where
``power > 0``; ``alpha = min(0.99, opacity exp(power))``, skipped where ``alpha < 1/255``; the pixel
stops *before* the Gaussian that would bring its transmittance below 1e-4.
``colour = sum_k c_k alpha_k T_k + T_final background``, ``alpha_out = 1 - T_final``,
``depth = sum_k z_k alpha_k T_k``.

Backward (back to front from each pixel's last composited Gaussian, T recovered by division,
"colour behind" accumulators), with ``B_k = sum_{j>k} c_j alpha_j T_j + T_final background``:
``dC/dalpha_k = c_k T_k - B_k / (1 - alpha_k)``, ``dD/dalpha_k = z_k T_k - D_k / (1 - alpha_k)``,
``dA/dalpha_k = T_final / (1 - alpha_k)``; then the chain rule through the clamp (zero where it is
active, unless ``clamp_gradient == "reference"``), ``exp`` and the quadratic form. Gradients are
scatter-added per Gaussian; all 16 lanes of a packet walk the same list position so every scatter
of an iteration targets one Gaussian (docs/rasteriser_notes.md, "Scatter
contention").
"""

import sys
import typing
from dataclasses import dataclass

import drjit as dr

from usplat_dr.render.binning import ALPHA_MIN, Bins

#: A pixel stops before the Gaussian that would bring its transmittance below this (3DGS).
T_MIN = 1e-4
#: Alpha is clamped at this value so that T never reaches 0 (3DGS).
ALPHA_MAX = 0.99
#: Floats per (tile, Gaussian) record: u, v, conic a, b, c, opacity, r, g, b, z, Gaussian index
#: (bit pattern), padding. 16 floats = 64 bytes = one packet gather (2.2x faster forward than
#: ten scalar gathers: docs/rasteriser_notes.md, "Tiles, records and the benchmark scene").
RECORD = 16
#: Lanes per packet for the packet-uniform backward start (16-lane AVX-512; harmless elsewhere).
PACKET = 16


@dataclass
class PixelLanes:
    """One lane per pixel slot, tile-major so that one ``tile_size``^2 block is one tile.

    ``px, py`` (``Float``): sample position (j + 0.5, i + 0.5). ``tile`` (``UInt32``): global tile
    index. ``in_image`` (``Bool``): false for the padding of partial tiles. ``pixel`` (``UInt32``):
    row-major index ``b H W + i W + j``; ``color_index`` (``UInt32``): ``b 3 H W + i W + j``.
    ``batch`` (``UInt32``). ``hw`` (``UInt32``, opaque scalar): H W.
    """

    px: object
    py: object
    tile: object
    in_image: object
    pixel: object
    color_index: object
    batch: object
    hw: object


def padded_count(n: int) -> int:
    """``n`` Gaussians rounded up to a bucket: 4 buckets per power of two (at most 25 % more,
    and at least 1,024), so that a kernel whose target size is baked in (``ReduceMode.Expand``)
    is compiled once per bucket, not once per count.

    Examples:
        >>> [padded_count(n) for n in (1, 1024, 1025, 8192, 8193, 131072, 150000)]
        [1024, 1024, 1280, 8192, 10240, 131072, 163840]
    """
    if n <= 1024:
        return 1024
    step = 1 << max((n - 1).bit_length() - 3, 0)
    return -(-n // step) * step


def _types(x):
    mod = sys.modules[type(x).__module__]
    return mod.Float, mod.UInt32, mod.ArrayXf


def _power(rec, px, py):
    dx = rec[0] - px
    dy = rec[1] - py
    power = dr.fma(-0.5, dr.fma(rec[2], dx * dx, rec[4] * (dy * dy)), -(rec[3] * (dx * dy)))
    return dx, dy, power


class Composite(dr.CustomOp):
    """Composite per-Gaussian splats into images; see the module docstring for the equations.

    Differentiable inputs (``Float``, one lane per Gaussian): ``u, v`` (pixels), ``ca, cb, cc``
    (conic), ``opacity``, ``r, g, b`` (colour), ``z`` (depth). Non-differentiable: ``bins``
    (``Bins``), ``lanes`` (``PixelLanes``), ``background`` (``list`` of 3 ``Float``, one lane per
    image), ``n_pix`` (``int``: B H W), ``clamp_gradient`` (``str``).
    Outputs (row-major): colour (``Float``, [B, 3, H, W]), alpha and depth (``Float``, [B, H, W]).
    """

    # No runtime type-check wrappers here: Dr.Jit maps ``set_grad_in`` names to the parameters
    # of ``eval`` itself, and a wrapper (jaxtyping's import hook in our tests) would silently
    # disconnect the gradients.
    @typing.no_type_check
    def eval(self, u, v, ca, cb, cc, opacity, r, g, b, z, bins: Bins, lanes: PixelLanes,
             background, n_pix: int, clamp_gradient: str, backward_scatter: str = "lanes"):
        Float, UInt32, ArrayXf = _types(u)
        self.lanes = lanes
        self.num_gaussians = dr.width(u)
        self.clamp_gradient = clamp_gradient
        self.backward_scatter = backward_scatter

        # ---- Per-pair records (one 64-byte record per (tile, Gaussian) pair) ----
        gid = bins.pair_gid
        zero = dr.zeros(Float, dr.width(u))
        fields = [u, v, ca, cb, cc, opacity, r, g, b, z,
                  dr.reinterpret_array(Float, dr.arange(UInt32, dr.width(u)))]
        fields += [zero] * (RECORD - len(fields))
        per_gaussian = dr.ravel(ArrayXf(fields))
        if bins.num_pairs is None:  # fixed capacity: only lanes before the last tile's end
            used = dr.arange(UInt32, dr.width(gid)) < bins.kept
            rec = dr.gather(ArrayXf, per_gaussian, gid, active=used, shape=(RECORD, 1))
        else:
            rec = dr.gather(ArrayXf, per_gaussian, gid, shape=(RECORD, 1))
        self.records = dr.ravel(rec)

        start = dr.gather(UInt32, bins.tile_start, lanes.tile)
        end = dr.gather(UInt32, bins.tile_end, lanes.tile)
        self.start = start
        px, py, records = lanes.px, lanes.py, self.records

        # ---- Compositing, front to back ----
        def cond(i, T, cr, cg, cb_, depth, last, alive):
            return alive & (i < end)

        def body(i, T, cr, cg, cb_, depth, last, alive):
            rec = dr.gather(ArrayXf, records, i, shape=(RECORD, 1))
            _, _, power = _power(rec, px, py)
            alpha = dr.minimum(ALPHA_MAX, rec[5] * dr.exp(power))
            use = (power <= 0) & (alpha >= ALPHA_MIN)
            test_T = T * (1.0 - alpha)
            stop = use & (test_T < T_MIN)  # stop before compositing this Gaussian
            use &= ~stop
            w = alpha * T  # compositing weight
            cr = dr.select(use, dr.fma(rec[6], w, cr), cr)
            cg = dr.select(use, dr.fma(rec[7], w, cg), cg)
            cb_ = dr.select(use, dr.fma(rec[8], w, cb_), cb_)
            depth = dr.select(use, dr.fma(rec[9], w, depth), depth)
            T = dr.select(use, test_T, T)
            last = dr.select(use, i + 1, last)
            return i + 1, T, cr, cg, cb_, depth, last, alive & ~stop

        n = dr.width(start)
        state = (
            UInt32(start),              # list position
            dr.full(Float, 1.0, n),     # transmittance
            dr.zeros(Float, n), dr.zeros(Float, n), dr.zeros(Float, n),  # colour
            dr.zeros(Float, n),         # depth
            UInt32(start),              # one past the last composited list position
            lanes.in_image,             # pixel still compositing
        )
        _, T, cr, cg, cb_, depth, last, _ = dr.while_loop(state, cond, body,
                                                          label="usplat_composite")
        # One kernel for the loop: each lazily consumed output would otherwise re-run it.
        dr.eval(T, cr, cg, cb_, depth, last)
        self.T_final, self.last = T, last
        self.background = [dr.gather(Float, c, lanes.batch) for c in background]

        # ---- Outputs, scattered from tile-major lanes to row-major images ----
        hw = lanes.hw
        color = dr.zeros(Float, 3 * n_pix)
        alpha_out = dr.zeros(Float, n_pix)
        depth_out = dr.zeros(Float, n_pix)
        for k, ch in enumerate((cr, cg, cb_)):
            dr.scatter(color, dr.fma(T, self.background[k], ch), lanes.color_index + k * hw,
                       active=lanes.in_image)
        dr.scatter(alpha_out, 1.0 - T, lanes.pixel, active=lanes.in_image)
        dr.scatter(depth_out, depth, lanes.pixel, active=lanes.in_image)
        return color, alpha_out, depth_out

    @typing.no_type_check
    def backward(self):
        lanes, records = self.lanes, self.records
        Float, UInt32, ArrayXf = _types(self.T_final)
        g_color, g_alpha, g_depth = self.grad_out()
        active = lanes.in_image
        hw = lanes.hw
        gc = [dr.gather(Float, g_color, lanes.color_index + k * hw, active=active)
              for k in range(3)]
        ga = dr.gather(Float, g_alpha, lanes.pixel, active=active)
        gd = dr.gather(Float, g_depth, lanes.pixel, active=active)
        T_final, last, start = self.T_final, self.last, self.start
        px, py = lanes.px, lanes.py
        reference_clamp = self.clamp_gradient == "reference"

        n_g = self.num_gaussians
        packet = self.backward_scatter == "packet"
        if packet:  # one gradient record per Gaussian, the count padded to a bucket
            record_grads = dr.zeros(Float, RECORD * padded_count(n_g))
        else:
            grads = [dr.zeros(Float, n_g) for _ in range(10)]

        # ---- Packet-uniform start: every lane walks from its packet's furthest position ----
        packet_last = dr.block_reduce(dr.ReduceOp.Max, last, PACKET)
        first = dr.gather(UInt32, packet_last, dr.arange(UInt32, dr.width(last)) // PACKET)

        def cond(i, T, br, bg, bb, bd):
            return i > start

        def body(i, T, br, bg, bb, bd):
            pos = i - 1
            rec = dr.gather(ArrayXf, records, pos, shape=(RECORD, 1))
            dx, dy, power = _power(rec, px, py)
            G = dr.exp(power)
            alpha_raw = rec[5] * G
            alpha = dr.minimum(ALPHA_MAX, alpha_raw)
            use = (pos < last) & (power <= 0) & (alpha >= ALPHA_MIN)
            one_m = 1.0 - alpha
            inv_one_m = dr.rcp(one_m)
            T = dr.select(use, T * inv_one_m, T)  # transmittance in front of this Gaussian
            w = alpha * T
            g_alpha = (gc[0] * dr.fma(rec[6], T, -br * inv_one_m)
                       + gc[1] * dr.fma(rec[7], T, -bg * inv_one_m)
                       + gc[2] * dr.fma(rec[8], T, -bb * inv_one_m)
                       + gd * dr.fma(rec[9], T, -bd * inv_one_m)
                       + ga * T_final * inv_one_m)
            br = dr.select(use, dr.fma(rec[6], w, br), br)
            bg = dr.select(use, dr.fma(rec[7], w, bg), bg)
            bb = dr.select(use, dr.fma(rec[8], w, bb), bb)
            bd = dr.select(use, dr.fma(rec[9], w, bd), bd)

            # d alpha / d alpha_raw: 0 where the 0.99 clamp is active (exact derivative).
            passes = use if reference_clamp else use & (alpha_raw < ALPHA_MAX)
            g_raw = dr.select(passes, g_alpha, 0.0)
            g_power = g_raw * alpha_raw
            values = (
                -g_power * dr.fma(rec[2], dx, rec[3] * dy),   # u
                -g_power * dr.fma(rec[4], dy, rec[3] * dx),   # v
                -0.5 * g_power * (dx * dx),                   # conic a
                -g_power * (dx * dy),                         # conic b
                -0.5 * g_power * (dy * dy),                   # conic c
                g_raw * G,                                    # opacity
                gc[0] * w, gc[1] * w, gc[2] * w,              # colour
                gd * w,                                       # depth
            )
            gid = dr.reinterpret_array(UInt32, rec[10])
            if packet:
                record = ArrayXf([*values, *([Float(0.0)] * (RECORD - len(values)))])
                dr.scatter_add(record_grads, record, gid, active=use,
                               mode=dr.ReduceMode.Expand)
            else:
                for target, value in zip(grads, values):
                    dr.scatter_add(target, value, gid, active=use, mode=dr.ReduceMode.Local)
            return pos, T, br, bg, bb, bd

        state = (first, Float(T_final), T_final * self.background[0],
                 T_final * self.background[1], T_final * self.background[2],
                 dr.zeros(Float, dr.width(T_final)))
        dr.while_loop(state, cond, body, label="usplat_composite_backward")
        if packet:
            rows = dr.gather(ArrayXf, record_grads, dr.arange(UInt32, n_g), shape=(RECORD, 1))
            grads = [Float(rows[k]) for k in range(10)]
        for name, grad in zip(("u", "v", "ca", "cb", "cc", "opacity", "r", "g", "b", "z"), grads):
            self.set_grad_in(name, grad)

    def name(self):
        return "usplat_composite"
