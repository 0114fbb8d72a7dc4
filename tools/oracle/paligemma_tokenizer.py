"""A small stand-in for PaliGemma's tokenizer (google/paligemma-3b-pt-224, gated on the hub).

A SentencePiece BPE model is trained here with the settings Gemma's tokenizer.model uses (byte fallback, split
digits, identity normalisation, no dummy prefix, whitespace kept as is; <pad> 0, <eos> 1, <bos> 2, <unk> 3,
<mask> 4) and written, with the tokenizer.json / tokenizer_config.json transformers derives from it, into a
Hugging Face hub cache under the real repository id, so that upstream's
`AutoTokenizer.from_pretrained("google/paligemma-3b-pt-224")` loads it offline exactly as it would load the real
one. Only the vocabulary is smaller; ids of the special tokens are Gemma's.
"""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import sentencepiece as spm

REPO_ID = "google/paligemma-3b-pt-224"
# A fixed, made-up revision: the cache layout needs one (refs/main names it).
REVISION = "7f1a0c1b5e0d4a2c9b3e8f6d5c4b3a2918070605"
VOCAB_SIZE = 640

CORPUS = [
    "pick up the red cube and place it in the bowl",
    "Pick up the blue block, then put it on the plate.",
    "open the top drawer and put the black bowl inside",
    "stack the green cube on top of the yellow one",
    "move the arm to the left; grasp the handle (gently!)",
    "Place the 2 blue blocks, then stack 3 more on the tray",
    "push the button 10 times: then wait 5 seconds",
    "put the sponge in the sink and turn on the water",
    "fold the towel in half twice and place it on the shelf",
    "rotate the knob by 90 degrees counter-clockwise",
    "Insert the peg into the hole, then release the gripper.",
    "grab the cup by its handle and pour the water into the pot",
    "the robot should pick the object closest to the camera",
    "wipe the table with the cloth, starting from the corner",
    "Sort the pieces by color: red, green, blue and yellow.",
    "Task: pick up the cube, State: 12 127 128 255 0 64;\nAction: ",
    "Task: open the drawer, State: 1 2 3 4 5 6 7 8 9 10 100 200;\nAction: ",
]


def train_model() -> bytes:
    """The serialized SentencePiece model (tokenizer.model)."""
    out = io.BytesIO()
    spm.SentencePieceTrainer.train(
        sentence_iterator=iter(CORPUS * 8),
        model_writer=out,
        model_type="bpe",
        vocab_size=VOCAB_SIZE,
        byte_fallback=True,
        split_digits=True,
        normalization_rule_name="identity",
        add_dummy_prefix=False,
        remove_extra_whitespaces=False,
        allow_whitespace_only_pieces=True,
        character_coverage=1.0,
        pad_id=0,
        eos_id=1,
        bos_id=2,
        unk_id=3,
        pad_piece="<pad>",
        eos_piece="<eos>",
        bos_piece="<bos>",
        unk_piece="<unk>",
        user_defined_symbols=["<mask>", "<start_of_turn>", "<end_of_turn>"],
        num_threads=1,
        minloglevel=2,
    )
    return out.getvalue()


def write_snapshot(snapshot: Path) -> None:
    """tokenizer.model plus what transformers writes for it (tokenizer.json, tokenizer_config.json, ...)."""
    from transformers import AutoTokenizer, GemmaTokenizer, PaliGemmaConfig

    snapshot.mkdir(parents=True, exist_ok=True)
    model = snapshot / "tokenizer.model"
    model.write_bytes(train_model())
    # transformers converts tokenizer.model to its fast form (the conversion PaliGemma's own tokenizer.json came
    # from) and saves it next to it, as the real repository ships both.
    tok = GemmaTokenizer.from_pretrained(str(snapshot), add_bos_token=True, add_eos_token=False)
    tok.save_pretrained(str(snapshot))
    cfg_path = snapshot / "tokenizer_config.json"
    cfg = json.loads(cfg_path.read_text())
    cfg["tokenizer_class"] = "GemmaTokenizer"
    cfg["add_bos_token"] = True
    cfg["add_eos_token"] = False
    for machine_specific in ("vocab_file", "is_local"):  # paths of this machine, not part of the repository
        cfg.pop(machine_specific, None)
    cfg_path.write_text(json.dumps(cfg, indent=2, sort_keys=True) + "\n")
    # AutoTokenizer reads the repository's config.json to find the tokenizer class: PaliGemma's, with the
    # vocabulary size of this tokenizer.
    PaliGemmaConfig(text_config={"vocab_size": tok.vocab_size}).save_pretrained(str(snapshot))
    # The saved files must load back through AutoTokenizer as the same tokenizer.
    again = AutoTokenizer.from_pretrained(str(snapshot))
    for text in CORPUS:
        assert again(text)["input_ids"] == tok(text)["input_ids"], text


def write_hub_cache(hub_cache: Path) -> Path:
    """Writes the tokenizer as the hub cache holds REPO_ID; returns the snapshot directory."""
    repo = hub_cache / ("models--" + REPO_ID.replace("/", "--"))
    if repo.exists():
        shutil.rmtree(repo)
    snapshot = repo / "snapshots" / REVISION
    write_snapshot(snapshot)
    (repo / "refs").mkdir(parents=True, exist_ok=True)
    (repo / "refs" / "main").write_text(REVISION)
    return snapshot


if __name__ == "__main__":
    import sys

    print(write_hub_cache(Path(sys.argv[1])))
