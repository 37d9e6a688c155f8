"""Fewer record bytes in the forward compositing loop, A/B: 32-byte (tile, Gaussian) records
(u, v, conic, opacity, z, Gaussian index) and a 16-byte per-Gaussian colour table gathered by
the index for the lanes that composite, against the rasteriser's 64-byte records. Forward only,
the Dr.Jit entry on the bench's pixel-aligned scene, interleaved; the images must be identical.

    python train/bench/records_ab.py --size 256 --threads 1 --rounds 15

Measured 2026-11-27 (AMD EPYC Zen 4, AVX-512, 1 thread, the other core busy with a training
run): 32-byte / 64-byte wall 0.99 at 256x256 (83.1 / 84.0 ms), 1.00 at 64x64 (3.71 / 3.70 ms):
no gain, not adopted (docs/rasteriser_notes.md). The third variant reads the 32-byte record and
no colour (images wrong, the time only): the bound on any smaller record, half precision among
them. Measured 2026-11-29 (AMD EPYC AVX2, 1 thread, the other core busy): 0.91 at 256x256,
0.94-0.95 at 64x64, the 32-byte record with its colour table 0.99 in the same runs.
"""

import argparse
import sys
import typing

import torch  # first, as users write

import usplat_dr  # noqa: F401  (chooses libLLVM before drjit is imported)

# isort: split
import drjit as dr

from usplat_dr.evaluation.timing import interleaved, machine_line
from usplat_dr.render import pipeline
from usplat_dr.render.binning import ALPHA_MIN
from usplat_dr.render.composite import ALPHA_MAX, T_MIN, Composite
from usplat_dr.render.pipeline import rasterize_drjit
from usplat_dr.render.scenes import pixel_aligned_scene

REC8 = 8


def _types(x):
    mod = sys.modules[type(x).__module__]
    return mod.Float, mod.UInt32, mod.ArrayXf

class Composite8(Composite):
    # False: the colour is not read at all (each pixel blends its depth as grey), so the loop
    # loads 32 bytes a pair and nothing else: the most that any smaller record (half-precision
    # colour and depth packed into the 64-byte record's place) could gain. The image is wrong
    # by design; only the time is read.
    colour_table = True

    @typing.no_type_check
    def eval(self, u, v, ca, cb, cc, opacity, r, g, b, z, bins, lanes, background, n_pix,
             clamp_gradient, backward_scatter="lanes"):
        Float, UInt32, ArrayXf = _types(u)
        self.lanes = lanes
        gid = bins.pair_gid
        idx = dr.reinterpret_array(Float, dr.arange(UInt32, dr.width(u)))
        geo = dr.ravel(ArrayXf([u, v, ca, cb, cc, opacity, z, idx]))
        records = dr.ravel(dr.gather(ArrayXf, geo, gid, shape=(REC8, 1)))
        colours = dr.ravel(ArrayXf([r, g, b, dr.zeros(Float, dr.width(u))]))
        start = dr.gather(UInt32, bins.tile_start, lanes.tile)
        end = dr.gather(UInt32, bins.tile_end, lanes.tile)
        px, py = lanes.px, lanes.py

        def cond(i, T, cr, cg, cb_, depth, last, alive):
            return alive & (i < end)

        def body(i, T, cr, cg, cb_, depth, last, alive):
            rec = dr.gather(ArrayXf, records, i, shape=(REC8, 1))
            dx = rec[0] - px
            dy = rec[1] - py
            power = dr.fma(-0.5, dr.fma(rec[2], dx * dx, rec[4] * (dy * dy)), -(rec[3] * (dx * dy)))
            alpha = dr.minimum(ALPHA_MAX, rec[5] * dr.exp(power))
            use = (power <= 0) & (alpha >= ALPHA_MIN)
            test_T = T * (1.0 - alpha)
            stop = use & (test_T < T_MIN)
            use &= ~stop
            w = alpha * T
            if self.colour_table:
                col = dr.gather(ArrayXf, colours, dr.reinterpret_array(UInt32, rec[7]),
                                shape=(4, 1), active=use)
            else:
                col = (rec[6], rec[6], rec[6])
            cr = dr.select(use, dr.fma(col[0], w, cr), cr)
            cg = dr.select(use, dr.fma(col[1], w, cg), cg)
            cb_ = dr.select(use, dr.fma(col[2], w, cb_), cb_)
            depth = dr.select(use, dr.fma(rec[6], w, depth), depth)
            T = dr.select(use, test_T, T)
            last = dr.select(use, i + 1, last)
            return i + 1, T, cr, cg, cb_, depth, last, alive & ~stop

        n = dr.width(start)
        state = (UInt32(start), dr.full(Float, 1.0, n), dr.zeros(Float, n), dr.zeros(Float, n),
                 dr.zeros(Float, n), dr.zeros(Float, n), UInt32(start), lanes.in_image)
        _, T, cr, cg, cb_, depth, last, _ = dr.while_loop(state, cond, body, label="c8")
        dr.eval(T, cr, cg, cb_, depth, last)
        bg = [dr.gather(Float, c, lanes.batch) for c in background]
        hw = lanes.hw
        color = dr.zeros(Float, 3 * n_pix)
        alpha_out = dr.zeros(Float, n_pix)
        depth_out = dr.zeros(Float, n_pix)
        for k, ch in enumerate((cr, cg, cb_)):
            dr.scatter(color, dr.fma(T, bg[k], ch), lanes.color_index + k * hw,
                       active=lanes.in_image)
        dr.scatter(alpha_out, 1.0 - T, lanes.pixel, active=lanes.in_image)
        dr.scatter(depth_out, depth, lanes.pixel, active=lanes.in_image)
        return color, alpha_out, depth_out


class Composite8NoColour(Composite8):
    colour_table = False


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=256, help="image edge in pixels")
    p.add_argument("--threads", type=int, default=1, help="Dr.Jit threads")
    p.add_argument("--rounds", type=int, default=15, help="timed rounds (ABBA)")
    args_ = p.parse_args()
    size, rounds = args_.size, args_.rounds
    from drjit.llvm.ad import TensorXf

    dr.set_thread_count(args_.threads)
    s = pixel_aligned_scene(size, size, seed=0)
    args = [TensorXf(t.contiguous()) if isinstance(t, torch.Tensor) else t for t in s.args()]

    def run(cls):
        def f():
            pipeline.Composite = cls
            out = rasterize_drjit(*args, check=False)
            dr.eval(out.color, out.alpha, out.depth)
            return out
        return f
    a, b = run(Composite)(), run(Composite8)()
    pipeline.Composite = Composite
    for k in ("color", "alpha", "depth"):
        x, y = getattr(a, k).numpy(), getattr(b, k).numpy()
        print(k, "max abs diff", abs(x - y).max())
    t = interleaved({"rec64": run(Composite), "rec32+colour": run(Composite8),
                     "rec32 only": run(Composite8NoColour)}, rounds, warmup=2)
    print(machine_line(), f"{size}x{size}, {args_.threads} thread(s)")
    for n, v in t.items():
        print(f"{n}: wall {v.wall:.2f} ms cpu {v.cpu:.2f} best {v.best:.2f}")
    print("ratio new/old", t["rec32+colour"].wall / t["rec64"].wall)
    print("ratio 32 bytes only (images wrong; the bound on smaller records)/old",
          t["rec32 only"].wall / t["rec64"].wall)


if __name__ == "__main__":
    main()
