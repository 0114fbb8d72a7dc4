"""Real-time chunking oracle for GR00T N1.7: lerobot's native N1.7 RTC (overlap prefix + velocity ramp) on a
committed tiny checkpoint.

Reads tests/fixtures/gr00t_n17/cam2_new (checkpoint, camera PNGs, state, instruction) without changing it, loads
it with gr00t_oracle.py's loader (GrootPolicy.from_pretrained, fp32, no autocast, stand-in hub cache), checks that
the committed case is reproduced bit for bit, then runs upstream once without RTC for a previous chunk (noise A)
and, with other noise (B), once without RTC and once per (inference_delay, execution_horizon) setting the way
lerobot's RTC rollout engine calls the policy (lerobot/rollout/context.py sets `policy.config.rtc_config`,
lerobot/rollout/inference/rtc.py pads / truncates the leftover to `execution_horizon` rows with
`_normalize_prev_actions_length`, then `predict_action_chunk(batch, inference_delay=, prev_chunk_left_over=)`).
GrootPolicy._prepare_n1_7_rtc_inputs turns that into GR00TN17.get_action options (action_horizon,
rtc_overlap_steps, rtc_frozen_steps, rtc_ramp_rate): the sampler's first overlap noise rows are replaced by the
leftover and each row's velocity is scaled (0 on frozen rows, an exponential ramp on the rest of the overlap).

The leftover is kept in robot units (lerobot's post-processor) as a client sends it to Tether, and its mapping
back through the pack step's own action normaliser is checked to give the normalised leftover upstream was fed
(within 1e-6; the case's action statistics have no degenerate dimension and the leftover stays inside the
[-1, 1] clip). The noise is injected by replacing torch.randn during the sampler call (gr00t_oracle.injected_noise).
Writes tests/fixtures/gr00t_n17_rtc/oracle.safetensors.

Usage: tools/oracle/run.sh gr00t_rtc_oracle.py [--out DIR]
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[2]
# gr00t_oracle only sets the hub cache when run as a script; the stand-in backbone repository lives there
os.environ["HF_HUB_CACHE"] = str(os.environ.get("TETHER_GR00T_HUB", _ROOT / "tests" / "fixtures" / "gr00t_hub"))

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402

import gr00t_oracle as go  # noqa: E402
import numpy as np  # noqa: E402
import safetensors  # noqa: E402
import torch  # noqa: E402
from smolvla_oracle import write_safetensors  # noqa: E402

SOURCE = "cam2_new"  # new_embodiment: 7 action values (arm 6, gripper 1), none degenerate, no decode transform
EXECUTED = 2  # actions of the previous chunk already run; the rest (4 of the 6 valid steps) is the leftover
NOISE_SEED = 20270  # one generator: the previous chunk's noise (A), then the new chunk's (B)
SETTINGS = [  # name, inference_delay, execution_horizon
    ("d1_h4", 1, 4),  # ordinary: the whole leftover overlaps, 1 frozen row, 3 ramped
    ("d2_h8", 2, 8),  # horizon past the leftover: zero-padded to 8 rows by the engine, stripped back to 4 upstream
    ("d5_h3", 5, 3),  # delay past the horizon: leftover truncated to 3 rows, frozen clamped to the overlap (3)
    ("d0_h4", 0, 4),  # no delay: nothing frozen, 4 ramped rows
    ("d1_h2", 1, 2),  # truncated leftover with a ramp: 2 rows, 1 frozen, 1 ramped
]
ROUNDTRIP_TOL = 1e-6

RULES = {
    "engine": "lerobot/rollout/context.py:266 sets policy.config.rtc_config = the RTCConfig (GrootConfig has no such "
    "field; it is added on the instance); lerobot/rollout/inference/rtc.py:320-327 passes "
    "_normalize_prev_actions_length(leftover, target_steps=rtc_config.execution_horizon) (rtc.py:83-94: first "
    "execution_horizon rows, or zero rows appended up to it) and inference_delay to predict_action_chunk; the "
    "leftover is the unconsumed rows of the model-space chunk (ActionQueue.get_left_over, action_queue.py:120-133)",
    "relative": "modeling_groot.py:356-366: GrootConfig.use_relative_actions -> no options, plain sampling",
    "strip": "modeling_groot.py:387-396: trailing rows whose |x| sums to 0 over batch and dims are dropped; all zero "
    "-> no options (plain sampling); interior zero rows are kept",
    "cut": "modeling_groot.py:398-403: more rows than the model's action_horizon -> the LAST action_horizon rows",
    "dims": "modeling_groot.py:408-419: dims cut or zero-padded to max_action_dim (padded dims of the overlap rows "
    "are 0, not noise)",
    "overlap": "modeling_groot.py:423-427: execution_horizon = rtc_config.execution_horizon (default: the stripped "
    "length); overlap = max(0, min(stripped length, execution_horizon)); 0 -> no options",
    "frozen": "modeling_groot.py:429-433: frozen = max(0, min(int(inference_delay or 0), overlap))",
    "ramp_rate": "modeling_groot.py:439: float(model config rtc_ramp_rate) (checkpoint config.json, default 6.0; "
    "GrootConfig.rtc_ramp_rate overrides it at load, modeling_groot.py:104-105)",
    "noise": "groot_n1_7.py:657-661: x0 = torch.randn((B, config.action_horizon, max_action_dim)) -- the full model "
    "horizon, drawn before the options are looked at",
    "prefix": "groot_n1_7.py:668-673: x0[:, :overlap] = action[:, len - overlap : len] (the TAIL of the stripped "
    "prefix; through the engine len == overlap unless execution_horizon > model horizon, so all of it)",
    "velocity_scale": "groot_n1_7.py:674-681: s = 1 everywhere, s[:frozen] = 0, n = overlap - frozen, "
    "t = linspace(0, 1, n + 2), r = 1 - exp(-rate t), r = r / max(r[-1], 1e-8), s[frozen:overlap] = r[1:-1] "
    "(per row, all dims)",
    "euler": "groot_n1_7.py:683-708: x_{k+1} = x_k + (1/steps) * v_k[:, -action_horizon:] * s for every step",
    "output": "modeling_groot.py:506-512: action_pred cut to min(model horizon, checkpoint delta_indices, chunk_size, "
    "n_action_steps) rows and the output feature's action dims",
}


def velocity_scale(overlap: int, frozen: int, rate: float, horizon: int) -> torch.Tensor:
    """Restatement of groot_n1_7.py:674-681 (checked below against upstream's Euler updates)."""
    s = torch.ones(horizon)
    s[:frozen] = 0.0
    t = torch.linspace(0.0, 1.0, overlap - frozen + 2)
    ramp = 1 - torch.exp(-rate * t)
    ramp = ramp / ramp[-1].clamp_min(1e-8)
    s[frozen:overlap] = ramp[1:-1]
    return s


def engine_length_function():
    """lerobot.rollout.inference.rtc._normalize_prev_actions_length, compiled from upstream's own source text:
    importing lerobot.rollout needs the `datasets` extra, which the oracle venv does not install."""
    import ast
    import importlib.util

    spec = importlib.util.find_spec("lerobot")
    path = Path(spec.submodule_search_locations[0]) / "rollout" / "inference" / "rtc.py"
    tree = ast.parse(path.read_text(), str(path))
    fn = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "_normalize_prev_actions_length"]
    assert len(fn) == 1
    scope: dict = {"torch": torch}
    exec(compile(ast.Module(body=fn, type_ignores=[]), str(path), "exec"), scope)
    return scope["_normalize_prev_actions_length"]


class Capture:
    """Records what GR00TN17.get_action received (inputs["action"], options) and, per Euler step, the action
    encoder's input x_k and the action decoder's output v_k."""

    def __init__(self, model):
        self.model = model
        self.calls: list[dict] = []
        self.xs: list[torch.Tensor] = []
        self.vs: list[torch.Tensor] = []
        orig = model.get_action

        def get_action(inputs, options=None):
            self.calls.append(
                {"action": inputs["action"].detach().clone() if "action" in inputs else None,
                 "options": dict(options) if options is not None else None}
            )
            out = orig(inputs, options)
            self.calls[-1]["action_pred"] = out["action_pred"].detach().clone()
            return out

        model.get_action = get_action
        head = model.action_head
        self.handles = [
            head.action_encoder.register_forward_pre_hook(lambda m, args: self.xs.append(args[0].detach().clone())),
            head.action_decoder.register_forward_hook(lambda m, args, out: self.vs.append(out.detach().clone())),
        ]

    def reset(self) -> None:
        self.calls.clear()
        self.xs.clear()
        self.vs.clear()

    def remove(self) -> None:
        del self.model.get_action
        for h in self.handles:
            h.remove()


def main() -> None:
    torch.set_num_threads(1)
    logging.getLogger("lerobot").setLevel(logging.ERROR)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="")
    args = p.parse_args()
    out = Path(args.out or go.REPO_ROOT / "tests" / "fixtures" / "gr00t_n17_rtc")
    out.mkdir(parents=True, exist_ok=True)
    go.ensure_tiny_hub()

    from lerobot.policies.rtc.configuration_rtc import RTCConfig
    from lerobot.policies.groot.processor_groot import GrootN17PackInputsStep

    _normalize_prev_actions_length = engine_length_function()

    spec = go.CASES[SOURCE]
    source = go.REPO_ROOT / "tests" / "fixtures" / "gr00t_n17" / SOURCE
    ckpt = (source / "checkpoint").resolve()
    with safetensors.safe_open(str(source / "oracle.safetensors"), "pt") as src:
        meta = src.metadata()
        committed = {k: src.get_tensor(k) for k in src.keys() if k.startswith(("input.", "out."))}
    cams = json.loads(meta["camera_keys"])
    files = json.loads(meta["input_files"])
    assert cams == [k for k, _ in spec["cameras"]] and meta["instruction"] == spec["instruction"]
    images = {k: go.decode_png(source / files[k]) for k in cams}
    for k in cams:
        assert np.array_equal(images[k], committed[f"input.image.{k}"][0].numpy()), k
    state = committed["input.state"]

    cfg, policy, pre, post, _ = go.load_policy(ckpt, spec)
    model = policy._groot_model
    head = model.action_head
    horizon, max_dim = int(model.config.action_horizon), int(model.config.max_action_dim)
    rate = float(model.config.rtc_ramp_rate)
    steps = head.num_inference_timesteps
    action_dim = cfg.output_features["action"].shape[0]
    pack = [s for s in pre.steps if isinstance(s, GrootN17PackInputsStep)][0]
    batch = {
        f"observation.images.{k}": torch.from_numpy(images[k]).permute(2, 0, 1).unsqueeze(0).contiguous() for k in cams
    }
    batch["observation.state"] = state.clone()
    batch["task"] = spec["instruction"]

    gen = torch.Generator().manual_seed(NOISE_SEED)
    shape = (1, horizon, max_dim)
    prev_noise = torch.randn(shape, generator=gen)
    noise = torch.randn(shape, generator=gen)

    cap = Capture(model)
    randn_log: list = []

    def run(n: torch.Tensor, **kw) -> torch.Tensor:
        cap.reset()
        before = len(randn_log)
        with go.injected_noise(head, n, randn_log):
            chunk = policy.predict_action_chunk(processed, **kw)
        if len(randn_log) != before + 1 or len(cap.calls) != 1 or len(cap.xs) != steps or len(cap.vs) != steps:
            raise RuntimeError(f"noise draws {randn_log[before:]}, get_action calls {len(cap.calls)}")
        return chunk

    t: dict[str, torch.Tensor] = {"input.prev_noise": prev_noise, "input.noise": noise}
    cases = []
    with torch.no_grad():
        processed = pre(batch)
        # the committed case, reproduced bit for bit (same loader, inputs and noise)
        again = run(committed["input.noise"])
        if not (torch.equal(again, committed["out.actions_chunk"]) and torch.equal(post(again.clone()), committed["out.actions"])):
            raise RuntimeError(f"{SOURCE} not reproduced")

        prev = run(prev_noise)
        assert cap.calls[0]["options"] is None and cap.calls[0]["action"] is None
        assert prev.shape == (1, go.VALID_HORIZON, action_dim)
        leftover_model = prev[:, EXECUTED:, :].contiguous()  # what lerobot's engine would keep (model space)
        prev_actions = post(leftover_model.clone()).float()  # robot units, as a client holds them (clipped decode)
        back = pack._normalize_action_groups_for_training(prev_actions.clone())  # upstream's action normaliser
        if back is None:
            raise RuntimeError("the pack step could not normalise the action groups")
        # a client only has robot units: values the decode clipped come back as +-1, the rest as they were
        roundtrip = float((back - leftover_model.clamp(-1.0, 1.0)).abs().max())
        if roundtrip > ROUNDTRIP_TOL:
            raise RuntimeError(f"robot-unit leftover maps back with error {roundtrip}")
        leftover_norm = back.float().contiguous()  # fed to upstream
        clipped = int((leftover_model.abs() > 1.0).sum())
        t["input.prev_actions"] = prev_actions
        t["input.prev_actions_normalized"] = leftover_norm.float()
        t["out.prev.actions_normalized"] = prev.float()

        plain = run(noise)
        t["out.no_rtc.actions_normalized"] = plain.float()
        t["out.no_rtc.actions"] = post(plain.clone()).float()

        direct = {}
        for name, delay, h in SETTINGS:
            policy.config.rtc_config = RTCConfig(enabled=True, execution_horizon=h)  # as lerobot/rollout/context.py
            prefix = _normalize_prev_actions_length(leftover_norm[0].clone(), target_steps=h)
            guided = run(noise, inference_delay=delay, prev_chunk_left_over=prefix.clone())
            call = cap.calls[0]
            opts = call["options"]
            n_left = leftover_norm.shape[1]
            length = min(n_left, h)  # rows left after the engine's truncation and upstream's zero-row strip
            overlap = min(length, h)
            frozen = max(0, min(delay, overlap))
            want = {"action_horizon": length, "rtc_overlap_steps": overlap, "rtc_frozen_steps": frozen,
                    "rtc_ramp_rate": rate}
            if opts != want:
                raise RuntimeError(f"{name}: options {opts}, expected {want}")
            fed = torch.zeros(1, length, max_dim)
            fed[:, :, :action_dim] = leftover_norm[:, :length]
            if not torch.equal(call["action"], fed):
                raise RuntimeError(f"{name}: prefix fed to get_action differs")
            x0 = noise.clone()
            x0[:, :overlap] = fed[:, length - overlap : length]
            if not torch.equal(cap.xs[0], x0):
                raise RuntimeError(f"{name}: sampler start differs from the restated prefix replacement")
            s = velocity_scale(overlap, frozen, rate, horizon)
            vel = s[None, :, None].expand(1, horizon, max_dim)
            x = cap.xs[0]
            for k in range(steps):
                x = x + (1.0 / steps) * cap.vs[k][:, -horizon:] * vel
                ref = cap.xs[k + 1] if k + 1 < steps else call["action_pred"]
                if not torch.equal(x, ref):
                    raise RuntimeError(f"{name}: Euler step {k} differs from the restated velocity scale")
            if not torch.equal(call["action_pred"][:, :frozen], x0[:, :frozen]):
                raise RuntimeError(f"{name}: frozen rows moved")
            t[f"input.{name}.prev_chunk_left_over"] = prefix.float()
            t[f"mid.{name}.x0"] = x0
            t[f"mid.{name}.velocity_scale"] = s
            t[f"out.{name}.action_pred"] = call["action_pred"].float()
            t[f"out.{name}.actions_normalized"] = guided.float()
            t[f"out.{name}.actions"] = post(guided.clone()).float()
            if torch.equal(guided, plain):
                raise RuntimeError(f"{name}: RTC changed nothing")

            # the same setting called directly with the whole leftover (no engine truncation): upstream then
            # replaces x0[:overlap] with the leftover's LAST overlap rows
            d = run(noise, inference_delay=delay, prev_chunk_left_over=leftover_norm.clone())
            dopts = cap.calls[0]["options"]
            tail = torch.zeros(1, overlap, max_dim)
            tail[:, :, :action_dim] = leftover_norm[:, n_left - overlap :]
            if dopts["action_horizon"] != n_left or not torch.equal(cap.xs[0][:, :overlap], tail):
                raise RuntimeError(f"{name}: direct call did not use the leftover's tail")
            direct[name] = "same as through the engine" if torch.equal(d, guided) else "differs (uses the tail)"

            cases.append({
                "name": name, "inference_delay": delay, "execution_horizon": h,
                "prefix_rows": f"leftover rows 0..{length - 1}" + (f", zero rows to {h}" if h > n_left else ""),
                "upstream_options": opts, "velocity_scale": [float(v) for v in s],
                "direct_call_with_whole_leftover": direct[name],
            })
        policy.config.rtc_config = None
    cap.remove()

    t = {k: v.detach().contiguous() for k, v in t.items()}
    for k, v in t.items():
        assert v.dtype == torch.float32, k
    info = {
        "versions": json.dumps(go.versions()),
        "source_case": f"tests/fixtures/gr00t_n17/{SOURCE} (checkpoint, inputs, state, instruction; reproduced "
        "bit for bit before the RTC runs)",
        "embodiment_tag": spec["tag"],
        "executed": str(EXECUTED),
        "cases": json.dumps(cases),
        "rules": json.dumps(RULES),
        "model": json.dumps({"action_horizon": horizon, "max_action_dim": max_dim, "rtc_ramp_rate": rate,
                             "num_inference_timesteps": steps, "valid_horizon": go.VALID_HORIZON,
                             "action_dim": action_dim}),
        "roundtrip": json.dumps({
            "normaliser": "GrootN17PackInputsStep._normalize_action_groups_for_training (q01/q99, clip to [-1, 1])",
            "decoder": "GrootN17ActionDecodeStep (post-processor)",
            "max_abs_error": roundtrip, "tolerance": ROUNDTRIP_TOL,
            "compared_with": "clamp(out.prev.actions_normalized[:, executed:], -1, 1)",
            "values_clipped_by_the_decode": clipped,
        }),
        "noise_injection": json.dumps({
            "how": "torch.randn replaced only while GR00TN17ActionHead.get_action_with_features ran "
            "(gr00t_oracle.injected_noise); one call per run",
            "noise": f"one torch.Generator().manual_seed({NOISE_SEED}): input.prev_noise = torch.randn({list(shape)}), "
            f"then input.noise = torch.randn({list(shape)})",
            "calls": randn_log[:1],
            "runs": len(randn_log),
        }),
        "replaced": meta["replaced"],
        "generator": "tools/oracle/run.sh gr00t_rtc_oracle.py",
    }
    write_safetensors(out / "oracle.safetensors", t, info)
    with safetensors.safe_open(str(out / "oracle.safetensors"), "pt") as f:
        assert set(f.keys()) == set(t) and all(torch.equal(f.get_tensor(k), t[k]) for k in t)
    print(f"wrote {out / 'oracle.safetensors'} (round trip {roundtrip:.3g}, {clipped} of {leftover_model.numel()} "
          f"leftover values clipped by the decode); direct calls: {direct}")


if __name__ == "__main__":
    sys.exit(main())
