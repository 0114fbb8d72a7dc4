#!/usr/bin/env python3
"""Stores the large oracle fixtures compressed in git and expands them before the tests run.

The oracle (tools/oracle) writes fixtures as plain files under tests/fixtures. Every file of at least 64 KiB there
lives in git inside one of the packs of tests/fixtures/packed/ instead: `<group>.json` lists each file (path
relative to tests/fixtures, size, sha256) and `<group>.xz` holds their contents, each distinct content once, in the
order of the list, as one xz stream. One stream per group of related fixtures lets LZMA's window find the weights
the cases of a family share (the pi0 / pi0.5 / FluxVLA checkpoints are mostly the same tensors) and the files that
are byte-identical are stored once. The expanded files are ignored by git (tests/fixtures/.gitignore, written here).

  unpack  writes every packed file that is missing or stale (the build runs it; quick when all are in place). A
          file that differs from its pack and from what unpack last wrote there was changed here (a regenerated
          fixture not packed yet): it is kept and reported, never overwritten.
  pack    rebuilds the packs from the files on disk after the oracle wrote them (tools/oracle/regenerate.sh runs
          it), rewrites tests/fixtures/.gitignore and takes the packed files out of git's index. A pack whose list
          is unchanged is left as it is, so re-packing never churns the stored streams.
  check   fails when a pack does not expand to its list, a packed file on disk differs from its pack, a packed
          path is tracked or not ignored by git, or a tracked fixture is large enough to belong in a pack.
"""
import argparse
import contextlib
import fcntl
import hashlib
import json
import lzma
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FIXTURES = ROOT / "tests" / "fixtures"
PACKS = FIXTURES / "packed"
GITIGNORE = FIXTURES / ".gitignore"
STATE = PACKS / ".unpacked.json"  # what unpack last wrote at each path: sha256, size, mtime (ignored by git)
LOCK = PACKS / ".lock"
THRESHOLD = 64 * 1024  # smaller fixtures (configs, sidecars, READMEs) stay plain files

# Fixture folders whose files share content go into one group, so that one xz window sees all of them.
GROUPS = {
    "pi": ["pi0", "pi05", "pi05_fluxvla", "pi0_rtc", "pi0_rtc_relative", "pi05_rtc", "pi05_rtc_relative",
           "paligemma_hub"],
    "smolvla": ["smolvla", "smolvla_rtc"],
    "gr00t": ["gr00t_hub", "gr00t_n16", "gr00t_n16_decode", "gr00t_n17", "gr00t_n17_relative", "gr00t_n17_rtc"],
    "vision": ["vision"],
    "tokenizer": ["tokenizer"],
}
# LZMA2 at preset 9 with a window larger than any group, so a tensor repeated anywhere in a group is found.
FILTERS = [{"id": lzma.FILTER_LZMA2, "preset": 9, "dict_size": 64 << 20}]


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def record(path, digest):
    st = path.stat()
    return {"sha256": digest, "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def recorded_sha256(rec):
    return rec["sha256"] if rec else None


def current_sha256(path, rec):
    """The file's sha256; taken from the record when size and mtime still match it, so a build with every file in
    place hashes nothing."""
    st = path.stat()
    if rec and rec["size"] == st.st_size and rec["mtime_ns"] == st.st_mtime_ns:
        return rec["sha256"]
    return sha256(path)


def manifest_path(group):
    return PACKS / f"{group}.json"


def load_manifest(group):
    p = manifest_path(group)
    return json.loads(p.read_text()) if p.exists() else None


def expand(group, manifest):
    """{sha256: bytes} for every distinct content of a pack, checked against its list."""
    stream = lzma.decompress((PACKS / manifest["stream"]).read_bytes())
    contents, offset = {}, 0
    for entry in manifest["files"]:
        if entry["sha256"] in contents:
            continue
        data = stream[offset:offset + entry["size"]]
        offset += entry["size"]
        if len(data) != entry["size"] or hashlib.sha256(data).hexdigest() != entry["sha256"]:
            raise SystemExit(f"fixture_packs: {group}.xz does not hold {entry['path']} as {group}.json lists it")
        contents[entry["sha256"]] = data
    if offset != len(stream):
        raise SystemExit(f"fixture_packs: {group}.xz holds {len(stream) - offset} bytes {group}.json does not list")
    return contents


def write_atomically(path, data):
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


@contextlib.contextmanager
def locked():
    """Two build folders (release, ci) may unpack into the same source tree at once."""
    PACKS.mkdir(parents=True, exist_ok=True)
    with open(LOCK, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        yield


def unpack(_args):
    with locked():
        state = json.loads(STATE.read_text()) if STATE.exists() else {}
        written, dirty = 0, False
        for group in GROUPS:
            manifest = load_manifest(group)
            if manifest is None:
                continue
            todo = []
            for entry in manifest["files"]:
                path = FIXTURES / entry["path"]
                if path.is_symlink() or (path.exists() and not path.is_file()):
                    raise SystemExit(f"fixture_packs: {path} is not a plain file; remove it and run unpack again")
                if path.exists() and current_sha256(path, state.get(entry["path"])) == entry["sha256"]:
                    fresh = record(path, entry["sha256"])
                    if state.get(entry["path"]) != fresh:
                        state[entry["path"]], dirty = fresh, True
                    continue
                if path.exists() and sha256(path) != recorded_sha256(state.get(entry["path"])):
                    print(f"fixture_packs: keeping {path.relative_to(ROOT)}: changed here, differs from "
                          f"packed/{group}.json (scripts/fixture_packs.py pack stores it)", file=sys.stderr)
                    continue
                todo.append(entry)
            if not todo:
                continue
            contents = expand(group, manifest)
            for entry in todo:
                write_atomically(FIXTURES / entry["path"], contents[entry["sha256"]])
                state[entry["path"]] = record(FIXTURES / entry["path"], entry["sha256"])
                written += 1
        if written or dirty:
            write_atomically(STATE, (json.dumps(state, indent=0, sort_keys=True) + "\n").encode())
        if written:
            print(f"fixture_packs: expanded {written} fixture files from tests/fixtures/packed")
    return 0


def git(*args, stdin=None, ok=(0,)):
    run = subprocess.run(["git", "-C", str(ROOT), *args], input=stdin, capture_output=True)
    if run.returncode not in ok:
        raise SystemExit(f"fixture_packs: git {' '.join(args[:2])} failed: {run.stderr.decode().strip()}")
    return run.stdout


def group_files(group):
    files = []
    for folder in GROUPS[group]:
        for dirpath, dirnames, filenames in os.walk(FIXTURES / folder):
            dirnames[:] = [d for d in dirnames if d != "__pycache__"]
            for name in filenames:
                path = Path(dirpath) / name
                if name.startswith(".") or path.is_symlink() or path.stat().st_size < THRESHOLD:
                    continue
                files.append(path.relative_to(FIXTURES).as_posix())
    return sorted(files)


def gitignore_pattern(rel):
    escaped = "".join("\\" + c if c in "\\*?[]!# " else c for c in rel)
    return "/" + escaped


def pack(_args):
    with locked():
        state = json.loads(STATE.read_text()) if STATE.exists() else {}
        all_paths = []
        for group in GROUPS:
            entries = [{"path": rel, "size": (FIXTURES / rel).stat().st_size, "sha256": sha256(FIXTURES / rel)}
                       for rel in group_files(group)]
            all_paths += [e["path"] for e in entries]
            old = load_manifest(group)
            stream = PACKS / f"{group}.xz"
            if old is not None and old["files"] == entries and stream.exists():
                continue
            if not entries:
                manifest_path(group).unlink(missing_ok=True)
                stream.unlink(missing_ok=True)
                continue
            seen, chunks = set(), []
            for e in entries:
                if e["sha256"] not in seen:
                    seen.add(e["sha256"])
                    chunks.append((FIXTURES / e["path"]).read_bytes())
            write_atomically(stream, lzma.compress(b"".join(chunks), format=lzma.FORMAT_XZ, filters=FILTERS))
            manifest = {"about": "tests/fixtures files stored in " + stream.name + " (scripts/fixture_packs.py)",
                        "stream": stream.name, "files": entries}
            write_atomically(manifest_path(group), (json.dumps(manifest, indent=1) + "\n").encode())
            print(f"fixture_packs: packed {len(entries)} files ({len(seen)} distinct) into packed/{stream.name}: "
                  f"{stream.stat().st_size} bytes")
            for e in entries:
                state[e["path"]] = record(FIXTURES / e["path"], e["sha256"])
        lines = ["# Written by scripts/fixture_packs.py pack: fixture files stored in packed/ and expanded by the",
                 "# build (scripts/fixture_packs.py unpack). Do not edit.", "/packed/.unpacked.json",
                 "/packed/.lock"] + [gitignore_pattern(p) for p in sorted(all_paths)]
        write_atomically(GITIGNORE, ("\n".join(lines) + "\n").encode())
        write_atomically(STATE, (json.dumps(state, indent=0, sort_keys=True) + "\n").encode())
        tracked = git("ls-files", "-z", "--", *[f"tests/fixtures/{p}" for p in all_paths]).split(b"\0")
        tracked = [t.decode() for t in tracked if t]
        if tracked:
            git("rm", "--cached", "-q", "--", *tracked)
            print(f"fixture_packs: {len(tracked)} packed files left git's index (git add tests/fixtures to commit)")
    return 0


def check(_args):
    problems = []
    packed = {}
    for group in GROUPS:
        manifest = load_manifest(group)
        if manifest is None:
            continue
        expand(group, manifest)  # exits with the reason when the stream and the list disagree
        for entry in manifest["files"]:
            packed[entry["path"]] = (group, entry)
    for rel, (group, entry) in sorted(packed.items()):
        path = FIXTURES / rel
        if not path.is_file():
            problems.append(f"{rel}: missing (scripts/fixture_packs.py unpack writes it)")
        elif path.stat().st_size != entry["size"] or sha256(path) != entry["sha256"]:
            problems.append(f"{rel}: differs from packed/{group}.json (scripts/fixture_packs.py pack stores it)")
    paths = [f"tests/fixtures/{rel}" for rel in sorted(packed)]
    tracked = [t for t in git("ls-files", "-z", "--", *paths).decode().split("\0") if t] if paths else []
    problems += [f"{t}: packed and also tracked by git" for t in tracked]
    ignored = set(git("check-ignore", "--no-index", "-z", "--stdin", stdin="\0".join(paths).encode(), ok=(0, 1))
                  .decode().split("\0")) if paths else set()  # exit 1: none ignored
    problems += [f"{p}: packed but not ignored by git (tests/fixtures/.gitignore)" for p in paths if p not in ignored]
    for t in git("ls-files", "-z", "--", "tests/fixtures").decode().split("\0"):
        p = ROOT / t
        if t and not t.startswith("tests/fixtures/packed/") and not p.is_symlink() and p.is_file() \
                and p.stat().st_size >= THRESHOLD:
            grouped = any(t.startswith(f"tests/fixtures/{f}/") for fs in GROUPS.values() for f in fs)
            problems.append(f"{t}: {p.stat().st_size} bytes tracked as a plain file (" +
                            ("scripts/fixture_packs.py pack stores it)" if grouped else
                             "add its folder to a group in scripts/fixture_packs.py, then pack)"))
    for p in problems:
        print("fixture_packs:", p)
    if not problems:
        print(f"fixture_packs: {len(packed)} packed fixture files match their packs")
    return 1 if problems else 0


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, fn in (("unpack", unpack), ("pack", pack), ("check", check)):
        sub.add_parser(name).set_defaults(fn=fn)
    args = parser.parse_args()
    return args.fn(args)


if __name__ == "__main__":
    sys.exit(main())
