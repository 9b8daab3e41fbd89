"""What ``train.compile`` fuses: ``python benchmarks/compiled_kernel_count.py [--device D] [--points N]``.

Runs each compiled part of a nerf-synthetic step forward and backward once eagerly, counting the operators that
launch a kernel (anisdf.benchmarks.opcount), and once compiled, counting the kernels inductor's generated code
calls: fused kernels (C++ on CPU, Triton on CUDA) and library calls (matrix products). The parts: the two SDF MLPs
with their closed-form normals (under an eikonal loss, as in training), and the radiance field with the NeuS
opacity. Counted, not timed: on a launch-bound GPU step each launch costs host time whatever its size.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch._inductor.utils import run_and_get_code

from anisdf.benchmarks.opcount import OpCounter
from anisdf.config import load_config
from anisdf.fields.radiance_field import RadianceField
from anisdf.fields.sdf_field import SDFField, mlp_with_input_grad
from anisdf.model_components import losses as L
from anisdf.model_components.neus_renderer import neus_alpha

_FUSED = re.compile(r"^\s+(?:cpp_fused_\w+\(|triton_\w+\.run\()", re.M)
_EXTERN = re.compile(r"extern_kernels\.\w+\(")


def _count(make: Callable[[], tuple], step: Callable[..., None], fns: tuple[Callable, ...]) -> tuple[int, ...]:
    """Eager operators, then compiled graphs, fused kernels and library calls of one ``step(make(), *fns)``
    (the inputs are made outside the count)."""
    counter = OpCounter()
    inputs = make()
    with counter:
        step(inputs, *fns)
    _, codes = run_and_get_code(step, make(), *(torch.compile(f, dynamic=True) for f in fns))
    calls = [c[c.find("def call("):] for c in codes]
    return (sum(counter.kernels.values()), len(codes), sum(len(_FUSED.findall(c)) for c in calls),
            sum(len(_EXTERN.findall(c)) for c in calls))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--points", type=int, default=30000)
    args = ap.parse_args()
    dev, n = torch.device(args.device), args.points
    torch._inductor.config.fx_graph_cache = False  # generate the code, so that it can be read
    torch._functorch.config.enable_autograd_cache = False
    cfg = load_config("nerf-synthetic", [])
    g = torch.Generator(dev).manual_seed(0)
    rf = RadianceField(cfg.appearance, cfg.geometry.feature_dim).to(dev)
    layers = [list(b.layers) for b in SDFField(cfg.geometry).to(dev).branches]

    def head_inputs() -> tuple[torch.Tensor, ...]:
        grad = torch.randn(n, 3, generator=g, device=dev, requires_grad=True)
        return (torch.randn(n, cfg.geometry.feature_dim, generator=g, device=dev, requires_grad=True), grad,
                F.normalize(grad, dim=-1).detach(), F.normalize(torch.randn(n, 3, generator=g, device=dev), dim=-1),
                torch.randn(n, generator=g, device=dev, requires_grad=True), torch.rand(n, generator=g, device=dev),
                torch.tensor(30.0, device=dev, requires_grad=True))

    def heads(inputs, color, alpha) -> None:  # noqa: ANN001
        feat, grad, normal, dirs, sdf, dt, inv_s = inputs
        a = alpha(sdf, grad, dirs, dt, inv_s, 0.5)
        rgb = color(dirs, feat, normal, dirs)["rgb"]  # a unit vector stands in for the position
        (rgb.sum() + a.sum()).backward()

    def mlp_inputs() -> list[tuple]:  # coarse and fine branch: inputs of their own widths; weights as leaves (in
        # training the weight-normed weights are computed once a step, outside)
        return [(torch.randn(n, lays[0].in_features, generator=g, device=dev, requires_grad=True),
                 [lay.weight.detach().requires_grad_(True) for lay in lays],
                 [lay.bias.detach().requires_grad_(True) for lay in lays]) for lays in layers]

    def sdf_mlps(inputs, mlp) -> None:  # noqa: ANN001
        loss = 0.0
        for h, weights, biases in inputs:
            out, hidden, grad = mlp(h, weights, biases)
            loss = loss + L.eikonal_loss(grad[:, :3]) + out.sum() + hidden.sum()
        loss.backward()

    print(f"forward and backward, {n} points on {dev} (torch {torch.__version__})")
    print("| part | eager operators | compiled: graphs, fused kernels + library calls |\n|---|---|---|")
    for name, make, step, fns in (
            ("SDF MLPs with closed-form normals", mlp_inputs, sdf_mlps, (mlp_with_input_grad,)),
            ("radiance field + NeuS opacity", head_inputs, heads, (rf.forward, neus_alpha))):
        eager, graphs, fused, extern = _count(make, step, fns)
        print(f"| {name} | {eager} | {graphs} graphs, {fused} + {extern} = {fused + extern} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
