#!/usr/bin/env python3
"""Runs a real GR00T N1.6 Eagle directory's own processor and writes what it produced, for Tether's opt-in test
`Gr00tN16EagleRelease.*` (scripts/check_isaac_gr00t.sh runs both).

Isaac-GR00T vendors that directory (gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2) instead of publishing it on the
hub or on PyPI, so no committed fixture can come from it. Given a copy, this script loads its Eagle3_VLProcessor
(trust_remote_code, under the transformers Isaac-GR00T pins) and calls it as Isaac-GR00T's N1.6 processor and
collator do: the chat template over one user turn (the language, then each image), process_vision_info, then the
processor on text and images. Recorded per case: the rendered text, input_ids and pixel_values of every image. Also
recorded: the ids of the shared tokenizer corpus (tests/fixtures/tokenizer/cases.jsonl) through the directory's
tokenizer, and the sha256 of every file read.

Usage: python eagle_release_check.py --eagle-dir DIR --out OUT
"""

import argparse
import hashlib
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")

import numpy as np  # noqa: E402
import torch  # noqa: E402
import transformers  # noqa: E402
from PIL import Image  # noqa: E402
from safetensors.torch import save_file  # noqa: E402

REPO = Path(__file__).resolve().parents[2]

# (language as the processor receives it, frame sizes as height x width after Isaac-GR00T's geometry). The language
# is what Tether passes on: formalised (lower case, letters, digits, spaces and "_") unless the checkpoint turns
# formalize_language off, so raw text is covered too.
CASES = [
    ("pick up the red cube and place it in the bowl", [(224, 224)]),
    ("stack the blue block on top of the green block", [(256, 256), (180, 320)]),
    ("perform the task", [(37, 100)]),
    ("open the top drawer then put the bowl inside", [(480, 640), (224, 224), (300, 200)]),
    ("Pick up the café mug, then STOP!  Move 10 cm left\tand lift 😀", [(224, 300)]),
    ("put_the_lid_on_the_pot 2", [(1000, 1400)]),
    ("", [(200, 200)]),
]


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def frame(rng, h, w):
    """A frame with smooth structure and noise, so resizing has edges and gradients to get right."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    base = np.stack([127 + 100 * np.sin(x / (3 + c) + y / (5 + 2 * c)) for c in range(3)], axis=-1)
    noise = rng.normal(0, 20, size=(h, w, 3))
    return np.clip(base + noise, 0, 255).astype(np.uint8)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--eagle-dir", required=True)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    eagle = Path(args.eagle_dir).resolve()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    processor = transformers.AutoProcessor.from_pretrained(str(eagle), trust_remote_code=True)
    tokenizer = processor.tokenizer
    rng = np.random.default_rng(2026)
    tensors, cases = {}, []
    for k, (language, sizes) in enumerate(CASES):
        files = []
        images = []
        for j, (h, w) in enumerate(sizes):
            name = f"case{k}_frame{j}.png"
            Image.fromarray(frame(rng, h, w)).save(out / name)
            files.append(name)
            images.append(Image.open(out / name).convert("RGB"))
        # Isaac-GR00T's Gr00tN1d6Processor._apply_vlm_processing, then Gr00tN1d6DataCollator.
        content = [{"type": "text", "text": language}, *[{"type": "image", "image": i} for i in images]]
        conversation = [{"role": "user", "content": content}]
        text = processor.apply_chat_template(conversation, tokenize=False, add_generation_prompt=False)
        image_inputs, _ = processor.process_vision_info([conversation])
        batch = processor(text=[text], images=image_inputs, return_tensors="pt", padding=True)
        tensors[f"case{k}.input_ids"] = batch["input_ids"][0].to(torch.int64).contiguous()
        for j, pixels in enumerate(batch["pixel_values"]):
            tensors[f"case{k}.pixels{j}"] = pixels[0].to(torch.float32).contiguous()
        cases.append({"language": language, "frames": files, "text": text,
                      "image_sizes": batch["image_sizes"].tolist()})
        print(f"case {k}: {len(batch['input_ids'][0])} tokens, images {batch['image_sizes'].tolist()}")
    save_file(tensors, str(out / "expected.safetensors"))

    corpus = [json.loads(line) for line in (REPO / "tests/fixtures/tokenizer/cases.jsonl").open(encoding="utf-8")]
    with open(out / "tokenizer_cases.jsonl", "w", encoding="utf-8") as f:
        for row in corpus:
            if "text" in row:
                ids = tokenizer(row["text"], add_special_tokens=False)["input_ids"]
                f.write(json.dumps({"text": row["text"], "ids": ids}, ensure_ascii=False) + "\n")

    meta = {
        "generator": "tools/oracle/eagle_release_check.py",
        "eagle_dir": str(eagle),
        "files": {p.name: sha256(p) for p in sorted(eagle.iterdir()) if p.is_file()},
        "processor": type(processor).__name__,
        "tokenizer": type(tokenizer).__name__,
        "image_token_index": json.loads((eagle / "config.json").read_text())["image_token_index"],
        "transformers": transformers.__version__,
        "torch": torch.__version__,
        "python": sys.version.split()[0],
        "cases": cases,
    }
    (out / "meta.json").write_text(json.dumps(meta, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
    print(f"wrote {len(cases)} cases and {len(corpus) - 1} tokenizer strings to {out}")


if __name__ == "__main__":
    main()
