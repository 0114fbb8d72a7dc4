#!/usr/bin/env python3
"""Checks relative links (files and #anchors) in the given Markdown files. Exit 1 on a broken one."""
import os, re, sys
PENDING = {"docs/backends.md", "docs/adding-a-model.md", "docs/serve-pipeline.md"}  # written separately
root = os.getcwd()

def strip_code(text):
    out, fence = [], False
    for line in text.split("\n"):
        if line.startswith("```"):
            fence = not fence; out.append(""); continue
        out.append("" if fence else re.sub(r"`[^`]*`", "", line))
    return out

def slugs(path):
    seen, res = {}, set()
    for line in strip_code(open(path).read()) if False else open(path).read().split("\n"):
        pass
    fence = False
    for line in open(path).read().split("\n"):
        if line.startswith("```"): fence = not fence; continue
        m = None if fence else re.match(r"(#{1,6}) +(.*)", line)
        if not m: continue
        s = m.group(2).strip().lower()
        s = re.sub(r"[^\w\- ]", "", s).replace(" ", "-")
        n = seen.get(s, 0); seen[s] = n + 1
        res.add(s if n == 0 else f"{s}-{n}")
    return res

bad = pending = checked = 0
for md in sys.argv[1:]:
    for lineno, line in enumerate(strip_code(open(md).read()), 1):
        for target in re.findall(r"\]\(([^)\s]+)\)", line):
            if re.match(r"[a-z]+:", target): continue
            checked += 1
            path, _, anchor = target.partition("#")
            full = os.path.normpath(os.path.join(os.path.dirname(md), path)) if path else md
            rel = os.path.relpath(full, root)
            if rel in PENDING and not os.path.exists(full):
                pending += 1; print(f"pending  {md}:{lineno}: {target}"); continue
            if not os.path.exists(full):
                bad += 1; print(f"BROKEN   {md}:{lineno}: {target} (no file {rel})"); continue
            if anchor and full.endswith(".md") and anchor not in slugs(full):
                bad += 1; print(f"BROKEN   {md}:{lineno}: {target} (no heading #{anchor} in {rel})")
print(f"{checked} links checked, {bad} broken, {pending} to pages written separately")
sys.exit(1 if bad else 0)
