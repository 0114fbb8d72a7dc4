"""Prints the camera keys (comma-separated) and a state of the checkpoint's width (comma-separated robot-unit values
0.1 * ((i % 7) - 3)), one line, for the benchmark and slow-suite scripts: from a lerobot config's features, or
(GR00T) from the processor config's first embodiment and its statistics.

Usage: python3 bench/checkpoint_inputs.py CHECKPOINT_DIR
"""
import json
import sys

d = sys.argv[1]
c = json.load(open(d + "/config.json"))
if "input_features" in c:
    cams = [k for k, v in c["input_features"].items() if v["type"] == "VISUAL" and "empty_camera" not in k]
    n = next(v["shape"][0] for v in c["input_features"].values() if v["type"] == "STATE")
else:
    m = json.load(open(d + "/processor_config.json"))["processor_kwargs"]["modality_configs"]
    tag, emb = next(iter(m.items()))
    stats = json.load(open(d + "/statistics.json"))[tag]["state"]
    cams = emb["video"]["modality_keys"]
    n = sum(len(stats[k]["min"]) for k in emb["state"]["modality_keys"])
print(",".join(cams), ",".join(f"{0.1 * ((i % 7) - 3):.1f}" for i in range(n)))
