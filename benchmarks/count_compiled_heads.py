"""What ``train.compile`` fuses: ``python benchmarks/count_compiled_heads.py [--device D] [--points N]``.

Runs the nerf-synthetic radiance field and the NeuS opacity forward and backward once eagerly, counting the
operators that launch a kernel (anisdf.benchmarks.opcount), and once compiled, counting the kernels inductor's
generated code calls: fused kernels (C++ on CPU, Triton on CUDA) and library calls (matrix products). Counted, not
timed: on a launch-bound GPU step each launch costs host time whatever its size.
"""

from __future__ import annotations

import argparse
import re

import torch
import torch.nn.functional as F
from torch._inductor.utils import run_and_get_code

from anisdf.benchmarks.opcount import OpCounter
from anisdf.config import load_config
from anisdf.fields.radiance_field import RadianceField
from anisdf.model_components.neus_renderer import neus_alpha

_FUSED = re.compile(r"^\s+(?:cpp_fused_\w+\(|triton_\w+\.run\()", re.M)
_EXTERN = re.compile(r"extern_kernels\.\w+\(")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--points", type=int, default=30000)
    args = ap.parse_args()
    dev, n = torch.device(args.device), args.points
    torch._inductor.config.fx_graph_cache = False  # generate the code, so that it can be read
    torch._functorch.config.enable_autograd_cache = False
    cfg = load_config("nerf-synthetic", [])
    rf = RadianceField(cfg.appearance, cfg.geometry.feature_dim).to(dev)
    g = torch.Generator(dev).manual_seed(0)

    def inputs() -> tuple[torch.Tensor, ...]:
        feat = torch.randn(n, cfg.geometry.feature_dim, generator=g, device=dev, requires_grad=True)
        grad = torch.randn(n, 3, generator=g, device=dev, requires_grad=True)
        dirs = F.normalize(torch.randn(n, 3, generator=g, device=dev), dim=-1)
        sdf = torch.randn(n, generator=g, device=dev, requires_grad=True)
        dt = torch.rand(n, generator=g, device=dev)
        return feat, grad, dirs, sdf, dt, torch.tensor(30.0, device=dev, requires_grad=True)

    def step(color, alpha, counter: OpCounter | None = None) -> None:  # noqa: ANN001
        feat, grad, dirs, sdf, dt, inv_s = inputs()
        normal = F.normalize(grad, dim=-1).detach()
        if counter is not None:
            counter.__enter__()
        a = alpha(sdf, grad, dirs, dt, inv_s, 0.5)
        rgb = color(feat, normal, dirs)["rgb"]
        (rgb.sum() + a.sum()).backward()
        if counter is not None:
            counter.__exit__(None, None, None)

    counter = OpCounter()
    step(rf, neus_alpha, counter)
    eager = sum(counter.kernels.values())
    _, codes = run_and_get_code(step, torch.compile(rf.forward, dynamic=True),
                                torch.compile(neus_alpha, dynamic=True))
    calls = [c[c.find("def call("):] for c in codes]
    fused = sum(len(_FUSED.findall(c)) for c in calls)
    extern = sum(len(_EXTERN.findall(c)) for c in calls)
    print(f"radiance field + NeuS opacity, forward and backward, {n} points on {dev} (torch {torch.__version__})")
    print("| | kernels launched |\n|---|---|")
    print(f"| eager operators | {eager} |")
    print(f"| compiled: {len(codes)} graphs, fused kernels + library calls | {fused} + {extern} = {fused + extern} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
