#!/usr/bin/env python3
"""Runs Isaac-GR00T's own StateActionProcessor (from a source checkout) on every committed GR00T N1.6 case and
compares it with what the fixtures hold, which Tether matches in `Gr00tN16Parity` and `Gr00tN16Decode`.

The N1.6 fixtures restate Isaac-GR00T's state encoding and action decoding, because Isaac-GR00T is not on PyPI. Given
a checkout, this script checks those restatements against the real code: for each case it builds
StateActionProcessor from the checkpoint's processor_config.json and statistics.json, as Gr00tN1d6Processor does;
then apply_state on the raw state must give the recorded per-group state encoding, and Gr00tN1d6Processor's
decode_action slicing with unapply_action (with the raw state, for relative groups) must give the recorded actions.

Usage: python isaac_state_action_check.py --isaac ISAAC_GR00T_CHECKOUT    (exit status 1 on a mismatch)
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from safetensors.numpy import load_file
from safetensors import safe_open

REPO = Path(__file__).resolve().parents[2]
FIXTURES = [REPO / "tests/fixtures/gr00t_n16", REPO / "tests/fixtures/gr00t_n16_decode"]
TOLERANCE = 1e-6  # relative to the largest value; the fixtures store float32


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--isaac", required=True, help="an Isaac-GR00T checkout (the directory holding gr00t/)")
    args = ap.parse_args()
    sys.path.insert(0, str(Path(args.isaac).resolve()))
    from gr00t.data.state_action.state_action_processor import StateActionProcessor

    failed = 0
    for root in FIXTURES:
        kwargs = json.loads((root / "checkpoint/processor_config.json").read_text())["processor_kwargs"]
        stats = json.loads((root / "checkpoint/statistics.json").read_text())
        processor = StateActionProcessor(
            modality_configs=kwargs["modality_configs"], statistics=stats,
            use_percentiles=kwargs["use_percentiles"], clip_outliers=kwargs["clip_outliers"],
            apply_sincos_state_encoding=kwargs["apply_sincos_state_encoding"],
            use_relative_action=kwargs["use_relative_action"])
        processor.eval()
        for case in sorted((root / "cases").iterdir()):
            t = load_file(str(case / "oracle.safetensors"))
            with safe_open(str(case / "oracle.safetensors"), "np") as f:
                tag = f.metadata()["embodiment_tag"]
            configs = processor.modality_configs[tag]
            state = {k: t[f"input.state.{k}"] for k in configs["state"].modality_keys}
            encoded = processor.apply_state(state, tag)
            diffs = {}
            for k in configs["state"].modality_keys:
                diffs[f"pre.state.{k}"] = np.abs(encoded[k].astype(np.float32) - t[f"pre.state.{k}"]).max()
            # Gr00tN1d6Processor.decode_action: rows [0, len(delta_indices)), columns per group in modality order,
            # widths from the statistics.
            horizon = len(configs["action"].delta_indices)
            pred = t["out.action_pred"][0]
            groups, start = {}, 0
            for k in configs["action"].modality_keys:
                dim = int(processor.norm_params[tag]["action"][k]["dim"])
                groups[k] = pred[:horizon, start:start + dim]
                start += dim
            decoded = processor.unapply_action(groups, tag, state=state)
            for k in configs["action"].modality_keys:
                diffs[f"out.action.{k}"] = np.abs(decoded[k].astype(np.float32) - t[f"out.action.{k}"][0]).max()
            scale = max(1.0, float(np.abs(t["out.actions"]).max()))
            worst = max(diffs.values())
            ok = worst <= TOLERANCE * scale
            failed += not ok
            verdict = "ok" if ok else "MISMATCH " + json.dumps({k: float(v) for k, v in diffs.items()})
            print(f"{root.name}/{case.name} ({tag}): {len(diffs)} groups, max |diff| {worst:.2e} "
                  f"(values up to {scale:.2f}) {verdict}")
    print("Isaac-GR00T StateActionProcessor:", "all cases match" if not failed else f"{failed} case(s) differ")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
