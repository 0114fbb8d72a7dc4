#!/usr/bin/env python3
"""A stand-in for the Hugging Face Hub and its CDN, on loopback, for the hub layer's integration tests.

Prints one JSON line {"hub": url, "cdn": url} once both servers listen, then serves until stdin closes.
`--repo ORG/NAME=DIR` (repeatable) also serves the files under DIR as that repository at COMMIT_MAIN (weights and
SentencePiece models through the CDN, as LFS files), e.g. a fixture checkpoint for `tether go`.
The hub is http://127.0.0.1:<port>; the CDN is http://localhost:<other port>, a different host name and port,
so a client that forwards its token across the redirect is caught. GET /_log on the hub returns every
request both servers received (method, path, headers), in order.
"""
import hashlib
import json
import os
import socket
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import unquote, urlsplit

COMMIT_MAIN = "0123456789abcdef0123456789abcdef01234567"
COMMIT_DEV = "fedcba9876543210fedcba9876543210fedcba98"
GOOD_TOKEN = "hf_good_token"
CUT_AFTER = 256 * 1024  # bytes sent before the first transfer of big.bin is cut


def pattern_bytes(n, seed):
    """Deterministic filler: sha256("<seed>:<i>") digests, concatenated (the C++ tests build the same)."""
    blocks = (hashlib.sha256(b"%d:%d" % (seed, i)).digest() for i in range((n + 31) // 32))
    return b"".join(blocks)[:n]


def git_sha1(data):
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


# path -> (content, stored in LFS?)
MAIN_FILES = {
    "config.json": (b'{"type": "smolvla", "chunk_size": 50}\n', False),
    "sub/dir/notes.txt": (b"nested file\n", False),
    "model.safetensors": (pattern_bytes(300 * 1024, 1), True),
    "big.bin": (pattern_bytes(1024 * 1024, 2), True),
    "corrupt.bin": (pattern_bytes(64 * 1024, 3), True),
    "norange.bin": (pattern_bytes(48 * 1024, 4), True),
}
DEV_FILES = dict(MAIN_FILES)
DEV_FILES["config.json"] = (b'{"type": "smolvla", "chunk_size": 10}\n', False)

REPOS = {
    "tether-test/tiny": {"refs": {"main": COMMIT_MAIN, "dev": COMMIT_DEV},
                         "commits": {COMMIT_MAIN: MAIN_FILES, COMMIT_DEV: DEV_FILES}, "gated": False},
    "tether-test/gated": {"refs": {"main": COMMIT_MAIN},
                          "commits": {COMMIT_MAIN: {"config.json": MAIN_FILES["config.json"]}}, "gated": True},
}
RENAMED = {"tether-test/old-name": "tether-test/tiny"}
LFS_SUFFIXES = (".safetensors", ".model", ".bin")


def repo_from_dir(directory):
    files = {}
    for root, _, names in os.walk(directory):
        for name in sorted(names):
            path = os.path.join(root, name)
            with open(path, "rb") as f:
                files[os.path.relpath(path, directory).replace(os.sep, "/")] = (f.read(), name.endswith(LFS_SUFFIXES))
    return {"refs": {"main": COMMIT_MAIN}, "commits": {COMMIT_MAIN: files}, "gated": False}


for i, arg in enumerate(sys.argv[1:]):
    if arg == "--repo":
        repo_id, directory = sys.argv[i + 2].split("=", 1)
        REPOS[repo_id] = repo_from_dir(directory)

BLOBS = {}  # sha256 -> content, what the CDN serves
for repo in REPOS.values():
    for files in repo["commits"].values():
        for content, lfs in files.values():
            if lfs:
                BLOBS[hashlib.sha256(content).hexdigest()] = content
CORRUPT_SHA = hashlib.sha256(MAIN_FILES["corrupt.bin"][0]).hexdigest()
BIG_SHA = hashlib.sha256(MAIN_FILES["big.bin"][0]).hexdigest()
NORANGE_SHA = hashlib.sha256(MAIN_FILES["norange.bin"][0]).hexdigest()  # the CDN ignores Range for it

LOG = []
LOG_LOCK = threading.Lock()
STATE = {"big_cut": False}


class Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server_name = "hub"

    def log_message(self, fmt, *args):  # keep test output clean
        pass

    def record(self):
        with LOG_LOCK:
            LOG.append({"server": self.server_name, "method": self.command, "path": self.path,
                        "headers": {k: v for k, v in self.headers.items()}})

    def send(self, status, headers=(), body=b""):
        self.send_response(status)
        for k, v in headers:
            self.send_header(k, v)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def do_HEAD(self):
        self.record()
        self.route()

    def do_GET(self):
        if self.path == "/_log":
            with LOG_LOCK:
                body = json.dumps(LOG).encode()
            return self.send(200, [("Content-Type", "application/json")], body)
        self.record()
        self.route()


class HubHandler(Handler):
    server_name = "hub"

    def auth_state(self):
        auth = self.headers.get("Authorization")
        if auth is None:
            return "none"
        return "good" if auth == "Bearer " + GOOD_TOKEN else "bad"

    def route(self):
        path = urlsplit(self.path).path
        parts = path.split("/")
        if path.startswith("/api/models/") and len(parts) >= 7 and parts[5] == "revision":
            return self.api(parts[3] + "/" + parts[4], unquote("/".join(parts[6:])))
        if len(parts) >= 6 and parts[3] == "resolve":
            return self.resolve(parts[1] + "/" + parts[2], unquote(parts[4]), unquote("/".join(parts[5:])))
        self.send(404, [("X-Error-Message", "no such route")])

    def repo_or_error(self, repo_id, revision, with_commit_header=False):
        if repo_id in RENAMED:
            return None, RENAMED[repo_id]
        repo = REPOS.get(repo_id)
        if repo is None:
            self.send(404, [("X-Error-Code", "RepoNotFound"), ("X-Error-Message", "Repository not found")])
            return None, None
        commit = repo["refs"].get(revision, revision if revision in repo["commits"] else None)
        if commit is None:
            self.send(404, [("X-Error-Code", "RevisionNotFound"), ("X-Error-Message", "Invalid rev id: " + revision)])
            return None, None
        return (repo, commit), None

    def api(self, repo_id, revision):
        found, renamed = self.repo_or_error(repo_id, revision)
        if renamed:
            return self.send(307, [("Location", self.path.replace(repo_id, renamed, 1))])
        if found is None:
            return
        repo, commit = found
        info = {"id": repo_id, "modelId": repo_id, "sha": commit, "private": False,
                "gated": "manual" if repo["gated"] else False,
                "siblings": [{"rfilename": p} for p in sorted(repo["commits"][commit])]}
        self.send(200, [("Content-Type", "application/json")], json.dumps(info).encode())

    def resolve(self, repo_id, revision, filename):
        found, renamed = self.repo_or_error(repo_id, revision)
        if renamed:
            # Relative redirect on the same host, as the hub answers for a renamed repo.
            return self.send(307, [("Location", self.path.replace("/" + repo_id + "/", "/" + renamed + "/", 1))])
        if found is None:
            return
        repo, commit = found
        if repo["gated"] and self.auth_state() != "good":
            status = 401 if self.auth_state() == "none" else 403
            return self.send(status, [("X-Error-Code", "GatedRepo"),
                                      ("X-Error-Message", "Access to model " + repo_id + " is restricted.")])
        files = repo["commits"][commit]
        if filename not in files:
            return self.send(404, [("X-Error-Code", "EntryNotFound"), ("X-Repo-Commit", commit),
                                   ("X-Error-Message", "Entry not found")])
        content, lfs = files[filename]
        if lfs:
            sha = hashlib.sha256(content).hexdigest()
            cdn = self.server.cdn_url + "/repos/" + sha[:2] + "/" + sha + "?X-Amz-Signature=deadbeef"
            body = b"Found. Redirecting to " + cdn.encode()
            return self.send(302, [("Location", cdn), ("X-Repo-Commit", commit),
                                   ("X-Linked-Etag", '"' + sha + '"'), ("X-Linked-Size", str(len(content))),
                                   ("ETag", 'W/"1a-redirect-page"')], body)
        self.send(200, [("X-Repo-Commit", commit), ("ETag", '"' + git_sha1(content) + '"'),
                        ("Content-Type", "text/plain")], content)


class CdnHandler(Handler):
    server_name = "cdn"

    def route(self):
        sha = urlsplit(self.path).path.rsplit("/", 1)[-1]
        content = BLOBS.get(sha)
        if content is None:
            return self.send(404)
        if sha == CORRUPT_SHA:
            content = content[:100] + bytes([content[100] ^ 0xFF]) + content[101:]
        start = 0
        rng = self.headers.get("Range")
        if rng and rng.startswith("bytes=") and rng.endswith("-") and sha != NORANGE_SHA:
            start = int(rng[len("bytes="):-1])
            if start >= len(content):
                return self.send(416, [("Content-Range", "bytes */%d" % len(content))])
        if sha == BIG_SHA and start == 0 and self.command == "GET" and not STATE["big_cut"]:
            # Announce the whole file, send part of it, then drop the connection.
            STATE["big_cut"] = True
            self.send_response(200)
            self.send_header("Content-Length", str(len(content)))
            self.end_headers()
            self.wfile.write(content[:CUT_AFTER])
            self.wfile.flush()
            self.close_connection = True
            self.connection.shutdown(socket.SHUT_RDWR)
            return
        if start > 0:
            return self.send(206, [("Content-Range", "bytes %d-%d/%d" % (start, len(content) - 1, len(content)))],
                             content[start:])
        self.send(200, [("Content-Type", "application/octet-stream")], content)


def main():
    hub = ThreadingHTTPServer(("127.0.0.1", 0), HubHandler)
    cdn = ThreadingHTTPServer(("127.0.0.1", 0), CdnHandler)
    hub.daemon_threads = cdn.daemon_threads = True
    hub.cdn_url = "http://localhost:%d" % cdn.server_address[1]
    for s in (hub, cdn):
        threading.Thread(target=s.serve_forever, daemon=True).start()
    print(json.dumps({"hub": "http://127.0.0.1:%d" % hub.server_address[1], "cdn": hub.cdn_url}), flush=True)
    sys.stdin.read()  # the test closes our stdin (or exits) when done
    os._exit(0)  # no orderly shutdown: it would wait out serve_forever's poll interval


if __name__ == "__main__":
    main()
