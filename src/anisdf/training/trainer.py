"""Training loop: dynamic ray batches, AdamW with warm-up + exponential decay, logging, checkpoints, resume.

The schedule (level activation, cos anneal, loss ramps, learning rate) reads one position, counted in the
schedule's own steps (``train.max_steps`` long): the step itself, or, with a time budget (``train.max_minutes``), the
fraction of the budget spent times ``max_steps``, so that the schedule always ends at the deadline whatever the
machine's speed (:meth:`Trainer.schedule_step`). The NeuS sharpness's learning rate also follows that position
(:meth:`Trainer.schedule_pace`): Adam moves its one parameter about one learning rate a step, so it would otherwise
sharpen with the number of steps a machine manages in the budget, not with the schedule.

A run folder holds ``config.yaml``, ``run.json`` (dataset path), ``checkpoints/last.pt``, ``tb/`` (TensorBoard),
``val/`` (validation images) and ``log.jsonl``. Checkpoints are atomic and carry every random state, so
``--resume`` continues exactly where an uninterrupted run would be (same seed, same result on CPU).

Under torchrun (``dist``, training/distributed.py) each rank draws its own rays and the gradients are averaged; only
rank 0 writes the run folder. A resume may change the number of ranks.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anisdf.config import Config
from anisdf.data.rays import RayBatch, RayDataset, eval_background
from anisdf.data.scene import Scene, capture_switch
from anisdf.errors import TrainingDiverged, surface_vanished
from anisdf.eval.metrics import psnr_from_mse
from anisdf.models.anisdf import AniSDFModel
from anisdf.models.per_image import refined_cameras_record
from anisdf.run_dir import RunDir
from anisdf.training.checkpoint import atomic_save
from anisdf.training.cpu_threads import ThreadTuner
from anisdf.training.distributed import Dist, rank_seed

log = logging.getLogger("anisdf")

LOSS_TERMS = ("rgb", "eikonal", "curvature", "orientation", "entropy", "mask", "camera", "total")
"""Every name AniSDFModel.losses can return."""


def lr_factor(step: int, cfg: Config, optimiser_step: int | None = None) -> float:
    """Linear warm-up from 1% over ``warmup_steps``, then exponential decay to ``final_lr_factor`` at the end, both
    at schedule step ``step``. With ``optimiser_step`` (under a time budget) the warm-up also lasts ``warmup_steps``
    optimiser steps: Adam's first updates need steps, not seconds, and a slow machine's schedule would otherwise end
    the warm-up in a few dozen steps (a sharpness that ran away and a lost surface in 90 s, benchmarks/RESULTS.md)."""
    o = cfg.optim
    done = step if optimiser_step is None else min(step, optimiser_step)
    warm = 0.01 + 0.99 * min(done / max(o.warmup_steps, 1), 1.0)
    span = max(cfg.train.max_steps - o.warmup_steps, 1)
    return warm * o.final_lr_factor ** (min(max(step - o.warmup_steps, 0), span) / span)


def build_model(cfg: Config, scene: Scene, device: torch.device) -> AniSDFModel:
    """The model for ``scene``: a background field for photos without masks, and for real photos (``auto``
    switches, :func:`~anisdf.data.scene.capture_switch`) camera corrections and appearance codes of the training
    images."""
    learn_bg = scene.background == "opaque" and scene.masks is None
    refine = capture_switch(cfg.cameras.refine, scene.format)
    codes = capture_switch(cfg.appearance.embedding, scene.format)
    trained = torch.zeros(scene.n_images, dtype=torch.bool)
    trained[list(range(scene.n_images)) if cfg.data.train_split == "all" else scene.splits["train"]] = True
    log.info("%s (%s): camera refinement %s, per-image appearance %s", scene.root.name, scene.format,
             "on" if refine else "off", f"on ({cfg.appearance.embedding_kind})" if codes else "off")
    return AniSDFModel(cfg, learn_background=learn_bg, trained=trained if refine or codes else None,
                       camera_poses=scene.cameras.c2w.cpu() if refine else None, image_codes=codes).to(device)


@dataclass
class TrainState:
    step: int = 0
    n_rays: int = 1024
    train_seconds: float = 0.0
    loss_ema: float = 0.0
    schedule_step: int = 0
    """Position in the schedule (see the module docstring); never moves back, also when a budget is raised."""
    pruned: float = 1.0  # the fraction of its marched samples the last step pruned (prune_after_query_below)


class Trainer:
    def __init__(self, cfg: Config, scene: Scene, out_dir: Path, device: torch.device, progress: bool = True,
                 dist: Dist | None = None):
        self.cfg, self.scene, self.out = cfg, scene, Path(out_dir)
        self.run_dir = RunDir(self.out)
        self.device = device
        self.dist = dist
        self.world_size = 1 if dist is None else dist.world_size
        self.is_main = dist is None or dist.is_main
        self.progress = progress and self.is_main
        # bf16 autocast for the radiance heads (the SDF stays float32, see SDFField.forward); CUDA only: on CPU it
        # has not been measured to help, and the tests set it to check the same code path without a GPU
        self.use_amp = cfg.train.amp and device.type == "cuda"
        # Tiny hash-table gradients squared in Adam become denormal floats, which are 10-100x slower on CPUs.
        torch.set_flush_denormal(True)
        torch.manual_seed(cfg.train.seed)
        # every random draw of a step comes from one generator on the training device: on CUDA, drawing on the
        # host and copying (randperm of ~250k samples, the occupancy jitter) cost milliseconds a step
        self.gen = torch.Generator(device).manual_seed(cfg.train.seed)
        # rays, marching jitter and loss subsets: one stream per rank (one process: the same generator)
        self.ray_gen = self.gen if dist is None else torch.Generator(device).manual_seed(
            rank_seed(cfg.train.seed, dist.rank))
        if cfg.geometry.encoding_backend != "torch":
            from anisdf.fields.hash_grid import load_fast_encoder

            # build (CPU) or compile and check (CUDA) the hash-grid kernels now, not inside the first step;
            # encoding_backend=fast stops here when the device has none
            load_fast_encoder(required=cfg.geometry.encoding_backend == "fast", device=device)
        self.model = build_model(cfg, scene, device)
        if dist is not None:
            dist.broadcast_module(self.model)
        if cfg.train.compile:
            self.model.compile_heads()
        o = cfg.optim
        groups = self.model.param_groups()
        groups[0]["lr"], groups[1]["lr"] = o.lr, o.lr_variance
        # one fused kernel per step instead of a few per parameter group: on CUDA the step is launch-bound, on CPU
        # the fused update reads each parameter once (a cpu-quick step: 2.7 ms against 10 ms, benchmarks/RESULTS.md)
        self.opt = torch.optim.AdamW(groups, betas=o.betas, eps=o.eps, weight_decay=o.weight_decay,
                                     fused=device.type in ("cuda", "cpu"))
        self.base_lrs = [g["lr"] for g in self.opt.param_groups]
        self.state = TrainState(n_rays=cfg.train.init_rays)
        self.train_data = RayDataset(scene, cfg.data.train_split, device=device, background=cfg.data.background)
        self.clock = time.perf_counter  # the time budget's clock (tests replace it)
        self.ckpt_path = self.run_dir.checkpoint
        self._writer = None
        self.step_hooks: list[Callable[[Trainer, dict[str, float]], None]] = []
        """Called after every step with its stats; their time is not training time (the live viewer renders there)."""

    # ----------------------------------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        return {
            "version": 1,
            "config": self.cfg.to_dict(),
            "model": self.model.state_dict(),
            "optimizer": self.opt.state_dict(),
            "state": vars(self.state).copy(),
            "generator": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "to_world": np.asarray(self.scene.to_world),
            "data": str(self.scene.root),
            "world_size": self.world_size,
        }

    def load_state_dict(self, ck: dict[str, Any]) -> None:
        self.model.load_state_dict(ck["model"])
        self.opt.load_state_dict(ck["optimizer"])
        # checkpoints written before the schedule position was kept: it was the step
        self.state = TrainState(**{"schedule_step": ck["state"]["step"], **ck["state"]})
        try:
            self.gen.set_state(ck["generator"])
        except (RuntimeError, ValueError):  # written on another kind of device: its random stream does not fit
            log.warning("the checkpoint was written on another kind of device; random draws restart from the "
                        "seed, so this resumed run is not bit-identical to an uninterrupted one")
        torch.set_rng_state(ck["torch_rng"])
        if self.dist is not None:
            self._load_rank_generator(ck)
        elif ck.get("world_size", 1) > 1:
            log.info("resuming a run of %d ranks in one process: its rays are drawn from rank 0's stream",
                     ck["world_size"])
        self.model.set_step(self.schedule_step())

    def _load_rank_generator(self, ck: dict[str, Any]) -> None:
        """This rank's ray stream: as saved when the checkpoint had as many ranks, else a fresh stream."""
        states = ck.get("rank_generators") or []
        if len(states) == self.world_size:
            try:
                self.ray_gen.set_state(states[self.dist.rank])
                return
            except (RuntimeError, ValueError):
                pass
        self.ray_gen.manual_seed(rank_seed(self.cfg.train.seed, self.dist.rank, self.state.step))
        if self.is_main:
            log.warning("the checkpoint was written by %d rank(s) and this run has %d: each rank draws its rays from "
                        "a fresh stream, so this resumed run is not bit-identical to an uninterrupted one",
                        ck.get("world_size", 1), self.world_size)

    @property
    def budget_seconds(self) -> float:
        return max(self.cfg.train.max_minutes, 0.0) * 60.0

    def schedule_step(self) -> int:
        """The schedule's position: the step, or with a time budget ``max_steps * seconds spent / budget`` (capped at
        ``max_steps``, and never below an earlier position)."""
        st = self.state
        if self.budget_seconds <= 0:
            return st.step
        return max(min(self.cfg.train.max_steps, int(self._budget_position())), st.schedule_step)

    def _budget_position(self) -> float:
        """Under a time budget, the schedule's unrounded position: ``max_steps * seconds spent / budget``."""
        return self.state.train_seconds / self.budget_seconds * self.cfg.train.max_steps

    def schedule_pace(self, bounded: bool = True) -> float:
        """Schedule steps per optimiser step so far: 1 without a time budget; with one, the budget's (unrounded)
        position over the steps taken, within [0.1, 4] if ``bounded``. The variance group's learning rate is multiplied
        by it, so that ``optim.lr_variance`` is a rate per schedule step: 90 s of cpu-quick on 2 cores (about 450 steps
        of its 1500) sharpen 3.3x faster a step, 10 minutes (about 3300 steps) 0.45x. At most 4: a budget of a few
        dozen steps would otherwise move the sharpness by a large factor each step, and lose the surface. From the
        checkpointed step and seconds, so a resume continues exactly; the same on every rank (rank 0's seconds)."""
        if self.budget_seconds <= 0 or self.state.step == 0:
            return 1.0
        pace = self._budget_position() / self.state.step
        return min(max(pace, 0.1), 4.0) if bounded else pace

    def schedule_done(self) -> bool:
        if self.budget_seconds > 0:
            return self.state.train_seconds >= self.budget_seconds
        return self.state.step >= self.cfg.train.max_steps

    def save(self, gather: bool = True) -> None:
        """Write the checkpoint (rank 0; with ranks, a collective that every rank calls unless ``gather`` is off)."""
        for p in self.model.parameters():
            if not torch.isfinite(p).all():
                raise TrainingDiverged("parameters became non-finite; not overwriting the last good checkpoint "
                                       f"{self.ckpt_path}")
        states = self.dist.gather_generator_states(self.ray_gen) if self.dist is not None and gather else None
        if self.is_main:
            atomic_save({**self.state_dict(), **({"rank_generators": states} if states else {})}, self.ckpt_path)
            if self.model.cameras is not None:  # the refined poses beside the originals, in the dataset's frame
                self.run_dir.write_refined_cameras(refined_cameras_record(
                    self.model.cameras, self.scene.image_paths, self.scene.root, self.scene.to_world, self.state.step))

    def write_run_files(self, status: str = "running") -> None:
        """``config.yaml`` and ``run.json`` (dataset, preset, normalisation, and the run's status: running, done,
        interrupted) and the number of ranks (rank 0 only)."""
        if not self.is_main:
            return
        self.out.mkdir(parents=True, exist_ok=True)
        self.run_dir.write_config(self.cfg.to_dict())
        self.run_dir.write_info({
            "data": str(Path(self.scene.root).resolve()), "format": self.scene.format,
            "preset": self.cfg.preset, "to_world": np.asarray(self.scene.to_world).tolist(),
            "status": status, "step": self.state.step, "schedule_step": self.state.schedule_step,
            "schedule": "time" if self.budget_seconds > 0 else "steps", "train_seconds": self.state.train_seconds,
            "world_size": self.world_size, "camera_refinement": self.model.cameras is not None,
            "appearance_codes": self.model.image_codes is not None,
        })

    @property
    def writer(self):
        if self._writer is None:
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(str(self.run_dir.tensorboard))
        return self._writer

    # ----------------------------------------------------------------------------------------- step
    def next_batch(self, n_rays: int) -> RayBatch:
        """This process's rays for a step (the distributed test replaces it to give one process the ranks' union)."""
        return self.train_data.sample(n_rays, self.ray_gen)

    def camera_rays(self, batch: RayBatch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The batch's rays, through the refined cameras from ``cameras.start_step`` on, and their appearance codes
        (None without)."""
        m, o, d = self.model, batch.origins, batch.directions
        if m.cameras is not None and self.state.schedule_step >= self.cfg.cameras.start_step:
            o, d = m.cameras(o, d, batch.cam_idx)
        return o, d, None if m.image_codes is None else m.image_codes(batch.cam_idx, len(batch))

    def train_step(self) -> dict[str, float]:
        st, cfg, model = self.state, self.cfg, self.model
        if not model.training:  # train() walks every submodule; validation is what switches it off
            model.train()
        st.schedule_step = self.schedule_step()
        model.set_step(st.schedule_step)
        rc = cfg.renderer
        if st.step % rc.grid_update_every == 0:
            warm = st.step < rc.grid_warmup_steps and st.step % (4 * rc.grid_update_every) == 0
            model.update_grid(self.gen, full=warm, job=self.dist)
            if not bool(model.grid.occupied.any()):  # no ray would have a sample again: nothing left to learn from
                raise surface_vanished(st.step, self.schedule_pace(bounded=False))
        f = lr_factor(st.schedule_step, cfg, st.step)  # without a budget the two are the same step
        pace = self.schedule_pace()
        for g, base in zip(self.opt.param_groups, self.base_lrs, strict=True):
            g["lr"] = base * f * (pace if g.get("name") == "variance" else 1.0)
        batch = self.next_batch(st.n_rays)
        origins, dirs, codes = self.camera_rays(batch)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.use_amp), model.cached_weights():
            out = model.render_rays(origins, dirs, batch.background, train=True, generator=self.ray_gen, codes=codes,
                                    prune_after_query=st.pruned < rc.prune_after_query_below)
            if self.dist is None:
                counts = (out.n_samples, out.n_marched)
                terms = model.losses(out, batch.rgb, batch.mask, self.gen)
            else:  # per-sample means weighted by this rank's share of all ranks' samples (distributed.py)
                counts = tuple(self.dist.sum_counts((out.n_samples, out.n_marched)))
                share = self.world_size * out.n_samples / max(counts[0], 1)
                terms = model.losses(out, batch.rgb, batch.mask, self.ray_gen, sample_share=share)
        if model.cameras is not None and st.schedule_step >= cfg.cameras.start_step and cfg.cameras.reg > 0:
            terms["camera"] = model.cameras.regulariser()
            terms["total"] = terms["total"] + cfg.cameras.reg * terms["camera"]
        loss = terms["total"]
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        # every number the step reports is read back at once: on a GPU each read waits for the queue to drain
        mse = torch.mean((out.rgb.detach().float() - batch.rgb) ** 2)
        if self.dist is None:
            names = list(terms)
            *term_vals, mse_val, inv_s = torch.stack([terms[k].detach().float() for k in names]
                                                     + [mse, out.inv_s.float()]).tolist()
            stats = dict(zip(names, term_vals, strict=True))
        else:  # gradients and reported figures: the mean over ranks, in one all-reduce
            stats, mse_val, inv_s = self._average_over_ranks(terms, mse, out.inv_s)
        value = stats["total"]
        if not math.isfinite(value) or (st.step > 100 and st.loss_ema > 0
                                        and value > cfg.loss.explode_factor * st.loss_ema):
            raise TrainingDiverged(  # before the optimiser step: the parameters are left as they were
                f"step {st.step}: loss {value:.4g} is {'not finite' if not math.isfinite(value) else 'exploding'} "
                f"(running mean {st.loss_ema:.4g}); the last good checkpoint {self.ckpt_path} is intact. "
                "Try a lower optim.lr or loss weights.")
        self.opt.step()
        self.model.variance.project_()
        (n_samples, n_marched), st.pruned = counts, 1.0 - counts[0] / max(counts[1], 1)
        # rays per step follow the sample budget of the full pass, and of the cheap pruning pass (x4); the budget
        # is per rank, the counts of all ranks (so every rank draws as many rays)
        budget = cfg.train.samples_per_step * self.world_size
        scale = min(budget / max(n_samples, 1), 4 * budget / max(n_marched, 1))
        st.n_rays = int(min(max(st.n_rays * scale, cfg.train.min_rays), cfg.train.max_rays))
        st.loss_ema = value if st.loss_ema == 0 else 0.98 * st.loss_ema + 0.02 * value
        st.step += 1
        stats.update(psnr=psnr_from_mse(mse_val), n_samples=n_samples,
                     n_rays=batch.origins.shape[0] * self.world_size, inv_s=inv_s,
                     lr=self.opt.param_groups[0]["lr"], schedule_step=st.schedule_step)
        return stats

    def _average_over_ranks(self, terms: dict[str, torch.Tensor], mse: torch.Tensor,
                            inv_s: torch.Tensor) -> tuple[dict[str, float], float, float]:
        """Average the gradients over ranks, and the loss terms (a rank without samples has fewer: each term is
        reported when some rank has it), the colour MSE and inv_s with them."""
        zero = mse.new_zeros(())
        vals = [terms[k].detach().float() if k in terms else zero for k in LOSS_TERMS]
        flags = [zero + (k in terms) for k in LOSS_TERMS]
        values = self.dist.average_grads(self.model.parameters(), torch.stack([*vals, *flags, mse, inv_s.float()]))
        *vals_flags, mse_val, inv_s_val = values.tolist()
        n = len(LOSS_TERMS)
        stats = {k: v for k, v, f in zip(LOSS_TERMS, vals_flags[:n], vals_flags[n:], strict=True) if f > 0}
        return stats, mse_val, inv_s_val

    @torch.no_grad()
    def validate(self) -> float:
        from anisdf.models.views import render_view, save_panel

        split = "test" if self.scene.splits.get("test") else "train"
        data = RayDataset(self.scene, split, device=self.device, background=eval_background(self.scene),
                          downscale=self.cfg.train.val_downscale)
        res = render_view(self.model, data, 0, self.scene, self.cfg.renderer.eval_chunk_rays)
        path = self.run_dir.validation_image(self.state.step)
        save_panel(path, res)
        self.writer.add_scalar("val/psnr", res["psnr"], self.state.step)
        with self.run_dir.validation_log.open("a") as f:
            f.write(json.dumps({"step": self.state.step, "time": round(self.state.train_seconds, 2),
                                "val_psnr": round(float(res["psnr"]), 4)}) + "\n")
        return res["psnr"]

    # ----------------------------------------------------------------------------------------- loop
    def fit(self, max_steps: int | None = None, max_minutes: float | None = None) -> dict[str, Any]:
        """Train until the schedule is done: ``train.max_steps`` steps, or with a time budget until the budget is
        spent (``max_minutes`` overrides the config's). ``max_steps`` stops earlier, at that step, leaving the schedule
        as it is (``stopped``; a resume goes on). Ctrl-C stops after the current step (``interrupted``). Either way
        the last checkpoint is written and ``run.json`` gives the status (``done`` once the schedule completed)."""
        from tqdm import tqdm

        cfg = self.cfg
        if max_minutes is not None:
            cfg.train.max_minutes = max_minutes
        timed = self.budget_seconds > 0
        self.write_run_files()
        # load (or build, the first time on a machine) the lazily loaded hash-grid kernels before the clock starts:
        # a one-off compile is not training time and must not eat into the budget's schedule
        with torch.no_grad():
            self.model.geometry.sdf(torch.zeros(1, 3, device=self.device))
        # on a shared CPU the fastest thread count is measured, not assumed (time budgets only: see cpu_threads)
        threads = torch.get_num_threads()
        # the first probe after 20 steps of 10 minutes, 4 of 2 minutes or less (busy core: benchmarks/RESULTS.md)
        warm = min(20, max(4, round(self.budget_seconds / 30)))
        tuner = ThreadTuner(threads, warmup=warm) if timed and self.device.type == "cpu" else None
        t_start = self.clock()
        t0_seconds = self.state.train_seconds
        total = cfg.train.max_steps
        desc = f"train ({cfg.train.max_minutes:g} min budget)" if timed else "train"
        bar = tqdm(total=total, initial=min(self.state.schedule_step, total), disable=not self.progress,
                   dynamic_ncols=True, desc=desc, unit="step")
        status = "done"
        last_stats: dict[str, float] = {}
        sps_window: list[tuple[float, int]] = []
        logf = self.run_dir.log.open("a") if self.is_main else open(os.devnull, "w")  # noqa: SIM115
        try:
            while not self.schedule_done():
                if max_steps and self.state.step >= max_steps:
                    status = "stopped"
                    break
                t = self.clock()
                stats = self.train_step()
                dt = self.clock() - t
                self.state.train_seconds = t0_seconds + (self.clock() - t_start)
                if self.dist is not None and timed:  # the time schedule and its end: rank 0's clock everywhere
                    self.state.train_seconds = self.dist.broadcast_float(self.state.train_seconds)
                if tuner is not None:
                    tuner.observe(dt, stats["n_samples"])
                sps_window = (sps_window + [(dt, stats["n_samples"])])[-20:]
                sps = sum(n for _, n in sps_window) / max(sum(d for d, _ in sps_window), 1e-9)
                stats["samples_per_s"] = sps
                last_stats = stats
                step = self.state.step
                bar.update(min(self.state.schedule_step, total) - bar.n if timed else 1)
                bar.set_postfix(loss=f"{stats['total']:.4f}", psnr=f"{stats['psnr']:.2f}",
                                samples_s=f"{sps / 1e3:.1f}k", rays=stats["n_rays"],
                                **({"step": step} if timed else {}), refresh=False)
                if self.is_main and (step % cfg.train.log_every == 0 or step == 1):
                    for k, v in stats.items():
                        self.writer.add_scalar(f"train/{k}", v, step)
                    logf.write(json.dumps({"step": step, "time": round(self.state.train_seconds, 2),
                                           **{k: round(v, 6) for k, v in stats.items()}}) + "\n")
                    logf.flush()
                if cfg.train.ckpt_every > 0 and step % cfg.train.ckpt_every == 0:
                    self.save()
                if self.is_main and cfg.train.val_every > 0 and step % cfg.train.val_every == 0:
                    self.validate()
                for hook in self.step_hooks:
                    t_hook = self.clock()
                    hook(self, stats)
                    t_start += self.clock() - t_hook
        except KeyboardInterrupt:
            status = "interrupted"
        finally:
            torch.set_num_threads(threads)
            bar.close()
            logf.close()
        if status == "done" and timed:  # the last step ran at the deadline: the schedule stands at its end
            self.state.schedule_step = total
            self.model.set_step(total)
        # interrupted, the ranks may stand at different points: rank 0 saves without the others' ray streams
        self.save(gather=status != "interrupted")
        self.write_run_files(status)
        if timed and status == "done":
            log.info("time budget of %g min spent: %d steps, schedule complete", cfg.train.max_minutes,
                     self.state.step)
        if self._writer is not None:
            self._writer.flush()
        return {"status": status, "step": self.state.step, "train_seconds": self.state.train_seconds,
                "schedule_step": self.state.schedule_step, "checkpoint": str(self.ckpt_path),
                **{k: last_stats[k] for k in ("psnr", "total") if k in last_stats}}
