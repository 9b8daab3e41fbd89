"""Hash-grid encoding speed: the PyTorch reference against the fast kernel (compiled C++ on CPU, Triton on CUDA).

Times, per grid setting, at the same points and table:

* ``fwd``: the encoding alone (no autograd graph);
* ``fwd+bwd``: encoding, then the gradient to the table and to the points;
* ``eikonal``: one step of the eikonal loss on analytic normals, as training does it: ``sdf = MLP(enc(x))``,
  ``n = d sdf / d x`` with ``create_graph=True``, ``loss = mean((|n| - 1)^2) + mean(sdf)``,
  ``loss.backward()``. The same small MLP (``L*F -> 64 -> 1``, Softplus) runs in both, so its cost is in both.

Lookups are counted as ``N * L * 8`` table rows per pass over the points. The "floor" is what a chain of
dependent random reads at about 15 ns each would give (1 / 15 ns per thread); the kernel beats it because
the reads of many points are independent and mostly hit the cache (one level's slice at a time). On CUDA
(``--device cuda``) the floor and the per-thread figures are not printed; timings synchronise the device.

Run ``python benchmarks/encoding_speed.py`` (or ``python -m anisdf.benchmarks.encoding``)
for a table, ``--json`` for one JSON object. The CLI calls
:func:`bench_encoding`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import torch
from torch import Tensor

from anisdf.fields.hash_grid import GridSpec, hash_encode_reference, kernel_info, load_fast_encoder, triton_info

FLOOR_NS_PER_LOOKUP = 15.0

DEFAULT_SETTINGS: dict[str, GridSpec] = {
    "fine (16 levels, log2 T 19)": GridSpec(),
    "fine, log2 T 17": GridSpec(log2_hashmap_size=17),
    "coarse (10 levels, log2 T 19)": GridSpec(n_levels=10),
}


def sync(device: torch.device | None) -> None:
    """Wait for the device's queued work (CUDA), so that wall-clock timings are true; nothing on CPU."""
    if device is not None and device.type == "cuda":
        torch.cuda.synchronize(device)


def _time(fn: Callable[[], Any], repeats: int, device: torch.device | None = None) -> tuple[float, float]:
    """(best, median) wall seconds over ``repeats`` runs after one warm-up run."""
    fn()
    sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return min(times), statistics.median(times)


def _cases(encode: Callable[[Tensor, Tensor, GridSpec], Tensor], x: Tensor, table: Tensor, spec: GridSpec,
           g: Tensor, mlp: torch.nn.Module) -> dict[str, Callable[[], Any]]:
    def fwd() -> Tensor:
        with torch.no_grad():
            return encode(x, table, spec)

    def fwd_bwd() -> None:
        xx = x.detach().requires_grad_(True)
        tt = table.detach().requires_grad_(True)
        encode(xx, tt, spec).backward(g)

    def eikonal() -> None:
        xx = x.detach().requires_grad_(True)
        tt = table.detach().requires_grad_(True)
        sdf = mlp(encode(xx, tt, spec))
        (n,) = torch.autograd.grad(sdf.sum(), xx, create_graph=True)
        loss = ((n.norm(dim=-1) - 1.0) ** 2).mean() + sdf.mean()
        loss.backward()

    return {"fwd": fwd, "fwd+bwd": fwd_bwd, "eikonal": eikonal}


def bench_encoding(n_points: int = 1 << 16, repeats: int = 3, *, reference: bool = True,
                   settings: dict[str, GridSpec] | None = None, seed: int = 0,
                   threads: int | None = None, device: str | torch.device = "cpu") -> dict[str, Any]:
    """Time reference and fast encodings on ``device``; returns a JSON-ready dict (see the module docstring).

    ``threads`` sets torch's thread count (used by both) for the run; default: leave it as it is.
    """
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return _bench(n_points, repeats, reference, DEFAULT_SETTINGS if settings is None else settings, seed,
                      torch.device(device))
    finally:
        torch.set_num_threads(previous)


def _bench(n_points: int, repeats: int, reference: bool, settings: dict[str, GridSpec],
           seed: int, device: torch.device) -> dict[str, Any]:
    fast = load_fast_encoder(device=device)
    threads = torch.get_num_threads()
    gen = torch.Generator().manual_seed(seed)
    out: dict[str, Any] = {
        "n_points": n_points,
        "repeats": repeats,
        "threads": threads,
        "device": str(device) if device.type == "cpu" else torch.cuda.get_device_name(device),
        "loadavg_before": list(os.getloadavg()),
        "kernel": kernel_info() if device.type == "cpu" else triton_info(device),
        "kernel_available": fast is not None,
        "floor_ns_per_lookup": FLOOR_NS_PER_LOOKUP,
        "settings": [],
    }
    for label, spec in settings.items():
        x = torch.rand(n_points, 3, generator=gen).to(device)
        table = ((torch.rand(spec.n_params, spec.features_per_level, generator=gen) - 0.5) * 0.2).to(device)
        g = torch.randn(n_points, spec.output_dim, generator=gen).to(device)
        torch.manual_seed(seed)
        mlp = torch.nn.Sequential(torch.nn.Linear(spec.output_dim, 64), torch.nn.Softplus(beta=100),
                                  torch.nn.Linear(64, 1)).to(device)
        lookups = n_points * spec.n_levels * 8
        row: dict[str, Any] = {"label": label, "spec": asdict(spec), "lookups_per_pass": lookups}
        impls: dict[str, Callable[[Tensor, Tensor, GridSpec], Tensor]] = {}
        if reference:
            impls["reference"] = hash_encode_reference
        if fast is not None:
            impls["fast"] = fast
        for name, encode in impls.items():
            res: dict[str, Any] = {}
            for case, fn in _cases(encode, x, table, spec, g, mlp).items():
                best, median = _time(fn, repeats, device)
                res[case] = {"best_s": best, "median_s": median, "points_per_s": n_points / best}
            res["fwd"]["lookups_per_s"] = lookups / res["fwd"]["best_s"]
            res["fwd"]["ns_per_lookup_per_thread"] = res["fwd"]["best_s"] * threads / lookups * 1e9
            row[name] = res
        if "reference" in impls and "fast" in impls:
            row["speedup"] = {c: row["reference"][c]["best_s"] / row["fast"][c]["best_s"]
                              for c in ("fwd", "fwd+bwd", "eikonal")}
            with torch.no_grad():
                row["max_abs_diff_fwd"] = float((hash_encode_reference(x, table, spec)
                                                 - impls["fast"](x, table, spec)).abs().max())
        out["settings"].append(row)
    out["floor_lookups_per_s"] = threads * 1e9 / FLOOR_NS_PER_LOOKUP
    out["loadavg_after"] = list(os.getloadavg())
    return out


def format_table(result: dict[str, Any]) -> str:
    """A plain-text table of :func:`bench_encoding`'s result."""
    n = result["n_points"]
    on_cpu = result.get("device", "cpu") == "cpu"
    where = f"{result['threads']} threads" if on_cpu else result["device"]
    lines = [f"hash-grid encoding, N = {n} points (2^{math.log2(n):.1f}), {where}, "
             f"best of {result['repeats']}; load average {result['loadavg_before'][0]:.1f}"]
    info = result["kernel"]
    if result["kernel_available"]:
        lines.append(f"kernel: {info['name']} ({' '.join(info['flags'] or [])}), build/load "
                     f"{(info['build_s'] or 0.0):.1f} s in this process")
    else:
        lines.append(f"kernel unavailable: {info['error']}")
    head = f"{'setting':32s} {'impl':9s} {'fwd pts/s':>11s} {'fwd+bwd':>11s} {'eikonal':>11s} " \
           f"{'lookups/s':>11s} {'ns/lookup/thr':>13s}"
    lines += [head, "-" * len(head)]
    for row in result["settings"]:
        for impl in ("reference", "fast"):
            if impl not in row:
                continue
            r = row[impl]
            lines.append(f"{row['label']:32s} {impl:9s} {r['fwd']['points_per_s']:11.3g} "
                         f"{r['fwd+bwd']['points_per_s']:11.3g} {r['eikonal']['points_per_s']:11.3g} "
                         f"{r['fwd']['lookups_per_s']:11.3g} "
                         + (f"{r['fwd']['ns_per_lookup_per_thread']:13.2f}" if on_cpu else f"{'-':>13s}"))
        if "speedup" in row:
            s = row["speedup"]
            lines.append(f"{'':32s} {'speedup':9s} {s['fwd']:10.1f}x {s['fwd+bwd']:10.1f}x {s['eikonal']:10.1f}x"
                         f"   (max |diff| {row['max_abs_diff_fwd']:.1e})")
    if on_cpu:
        lines.append(f"random-read floor: {result['floor_lookups_per_s']:.3g} lookups/s "
                     f"({result['floor_ns_per_lookup']:.0f} ns per lookup per thread)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=1 << 16, help="points per pass (default 65536)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--no-reference", action="store_true", help="time only the compiled kernel")
    parser.add_argument("--device", default="cpu", help="cpu (compiled C++ kernel) or cuda (Triton kernels)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    args = parser.parse_args(argv)
    from anisdf.errors import AnisdfError
    from anisdf.utils.devices import pick_device

    try:
        device = pick_device(args.device)
    except AnisdfError as err:
        parser.error(str(err))
    result = bench_encoding(args.points, args.repeats, reference=not args.no_reference, threads=args.threads,
                            device=device)
    print(json.dumps(result) if args.json else format_table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
