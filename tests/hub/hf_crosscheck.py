#!/usr/bin/env python3
"""Runs huggingface_hub itself against a cache directory, for the test that Tether and Python share one cache.

Usage: hf_crosscheck.py <cache_dir> <repo_id> <revision> <file>...
Downloads (or, with HF_HUB_OFFLINE=1, only looks up) each file with hf_hub_download, then scans the cache.
Prints one JSON object: {"paths": [...], "warnings": [...], "cached": [[commit, file, blob_path], ...]}.
"""
import json
import sys

from huggingface_hub import hf_hub_download, scan_cache_dir


def main():
    cache_dir, repo_id, revision, files = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
    paths = [hf_hub_download(repo_id, f, revision=revision, cache_dir=cache_dir) for f in files]
    info = scan_cache_dir(cache_dir)
    cached = []
    for repo in info.repos:
        for rev in repo.revisions:
            for f in rev.files:
                cached.append([rev.commit_hash, f.file_path.relative_to(rev.snapshot_path).as_posix(),
                               str(f.blob_path)])
    print(json.dumps({"paths": paths, "warnings": [str(w) for w in info.warnings], "cached": sorted(cached)}))


if __name__ == "__main__":
    main()
