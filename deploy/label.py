#!/usr/bin/env python3
"""Label pbrl preference pairs from a terminal.

A minimal client for the human teacher's HTTP/JSON API (protocol 1), standard library only.
The teacher serves the labelling page at `/` and this API beside it:

    GET  /api/v1/status?labeller=NAME              progress: open queries, answers, budget, ...
    GET  /api/v1/next?labeller=NAME[&exclude=ID]   200 with a pair, or 204 when nothing is open
    POST /api/v1/answer  {"labeller", "query", "choice", "took_ms", "replays"}
                         choice is "left" | "right" | "equal" | "skip"   -> {"ok": true, "answered": N}
    POST /api/v1/undo    {"labeller"}   withdraws this labeller's last answer -> {"query": ID};
                         409 {"error": "nothing to undo"} when there is none. The withdrawn
                         query comes back from the next /next call.

A pair is {"query", "display", "steps", "left": ATTEMPT, "right": ATTEMPT}; an attempt carries, per step
(steps + 1 entries), world positions in metres (z up): frames.spoon, frames.mouth, frames.head,
frames.arm (joint origins, end effector, spoon) and frames.food (one point per particle).
Errors are 4xx with {"error": "message"}. With --token T every call carries
"Authorization: Bearer T".

Interactive:
    python3 deploy/label.py --url http://127.0.0.1:8080 --name ana
prints a summary of each pair (computed from its frames) and asks a/b/=/s/u/q.

Non-interactive (tests):
    python3 deploy/label.py --url ... --name ana --answer alternate --count 5
answers 5 pairs (alternate cycles left, right, equal), one line each
("answered query 17: left"), and exits 0; exits 1 when no pair came for --timeout seconds.
"""

from __future__ import annotations

import argparse
import http.client
import json
import math
import re
import sys
import time
import urllib.error
import urllib.parse
import urllib.request

NAME_RE = re.compile(r"^[A-Za-z0-9 _.\-]{1,40}$")
CHOICES = ("left", "right", "equal", "skip")
ALTERNATE = ("left", "right", "equal")
NEAR_MOUTH_M = 0.05
HTTP_TIMEOUT_S = 30


class Unreachable(Exception):
    """No HTTP response: the teacher is down or the network is."""


class ApiError(Exception):
    """The teacher answered with an error status."""

    def __init__(self, status: int, message: str):
        super().__init__(f"HTTP {status}: {message}")
        self.status = status
        self.message = message


class Client:
    def __init__(self, url: str, name: str, token: str | None):
        self.base = url.rstrip("/")
        self.name = name
        self.token = token

    def call(self, method: str, path: str, body: dict | None = None, query: dict | None = None):
        """Returns (status, decoded JSON or None). Raises ApiError on >= 400, Unreachable."""
        url = self.base + path
        if query:
            url += "?" + urllib.parse.urlencode(query)
        headers = {"Accept": "application/json"}
        data = None
        if body is not None:
            data = json.dumps(body).encode()
            headers["Content-Type"] = "application/json"
        if self.token:
            headers["Authorization"] = "Bearer " + self.token
        req = urllib.request.Request(url, data=data, headers=headers, method=method)
        try:
            with urllib.request.urlopen(req, timeout=HTTP_TIMEOUT_S) as res:
                status = res.status
                raw = res.read()
        except urllib.error.HTTPError as e:
            raw = e.read() if e.fp else b""
            message = None
            try:
                message = json.loads(raw).get("error")
            except (ValueError, AttributeError):
                pass
            if not message:
                message = raw.decode("utf-8", "replace").strip()[:200] or e.reason or "error"
            raise ApiError(e.code, str(message)) from None
        except (urllib.error.URLError, http.client.HTTPException, OSError) as e:
            reason = getattr(e, "reason", e)
            raise Unreachable(f"teacher unreachable at {self.base}: {reason}") from None
        if status == 204 or not raw:
            return status, None
        try:
            return status, json.loads(raw)
        except ValueError:
            raise ApiError(status, "the teacher sent something that is not JSON") from None

    def status(self):
        return self.call("GET", "/api/v1/status", query={"labeller": self.name})[1]

    def next(self):
        """The next pair, or None when nothing is open (204)."""
        status, pair = self.call("GET", "/api/v1/next", query={"labeller": self.name})
        return pair if status != 204 else None

    def answer(self, query, choice: str, took_ms: int, deadline: float | None = None):
        """Posts an answer, retrying while the teacher is unreachable (until `deadline`).
        A 409 for a retry means the earlier try got through: it counts as done."""
        body = {
            "labeller": self.name,
            "query": query,
            "choice": choice,
            "took_ms": max(0, int(took_ms)),
            "replays": [0, 0],  # nothing is played back in a terminal
        }
        tries = 0
        while True:
            tries += 1
            try:
                return self.call("POST", "/api/v1/answer", body)[1] or {}
            except ApiError as e:
                # NOTE: not when another labeller answered first ("by_you": false).
                if e.status == 409 and tries > 1 and "another labeller" not in e.message:
                    return {"ok": True}
                raise
            except Unreachable as e:
                if deadline is not None and time.monotonic() > deadline:
                    raise
                if tries == 1:
                    print(f"{e}; retrying", file=sys.stderr, flush=True)
                time.sleep(1)

    def undo(self):
        return self.call("POST", "/api/v1/undo", {"labeller": self.name})[1] or {}


# ---------- the summary of an attempt ----------

def _dist(a, b) -> float:
    return math.sqrt(sum((float(x) - float(y)) ** 2 for x, y in zip(a, b)))


def summarise(attempt: dict) -> dict:
    """Spoon path length, top spoon speed per step, closest spoon-mouth distance, and the
    food particles that ended within 5 cm of the mouth, all from the attempt's frames."""
    frames = attempt.get("frames") or {}
    spoon = frames.get("spoon") or []
    mouth = frames.get("mouth") or []
    food = frames.get("food") or []
    steps = [_dist(spoon[i], spoon[i + 1]) for i in range(len(spoon) - 1)]
    closest = min(
        (_dist(s, m) for s, m in zip(spoon, mouth)),
        default=float("nan"),
    )
    near, n_food = 0, 0
    if food and mouth:
        last = food[-1] or []
        n_food = len(last)
        near = sum(1 for p in last if _dist(p, mouth[min(len(food), len(mouth)) - 1]) <= NEAR_MOUTH_M)
    return {
        "path": sum(steps),
        "top_speed": max(steps, default=0.0),
        "closest": closest,
        "near": near,
        "food": n_food,
        "frames": len(spoon),
    }


def describe(pair: dict) -> str:
    rows = []
    for label, side in (("A", "left"), ("B", "right")):
        s = summarise(pair.get(side) or {})
        rows.append(
            f"  {label}: spoon path {s['path']:.2f} m, top speed {s['top_speed'] * 100:.1f} cm/step, "
            f"closest to mouth {s['closest'] * 100:.1f} cm, "
            f"food ending near the mouth {s['near']}/{s['food']}"
        )
    return f"pair of {pair.get('steps', '?')} steps:\n" + "\n".join(rows)


def status_line(st: dict) -> str:
    budget = st.get("budget_left")
    bits = [
        f"open {st.get('open', '?')}",
        f"answered {st.get('answered', '?')}",
        f"budget left {'-' if budget is None else budget}",
        "training" if st.get("training") else "learner not running",
    ]
    if st.get("waiting"):
        bits.append("the learner is waiting for labels")
    return "[" + ", ".join(bits) + "]"


# ---------- the two modes ----------

def wait_for_pair(client: Client, timeout: float, quiet: bool):
    """Polls /next every second. Returns (pair, None), or (None, why) after `timeout`
    seconds without a pair."""
    deadline = time.monotonic() + timeout
    said_waiting = said_unreachable = False
    why = "nothing was open"
    while True:
        try:
            pair = client.next()
            said_unreachable = False
            why = "nothing was open"
            if pair is not None:
                return pair, None
            if not said_waiting and not quiet:
                print("no pairs to label right now; waiting for the learner", flush=True)
                said_waiting = True
        except Unreachable as e:
            why = str(e)
            if not said_unreachable:
                print(f"{e}; retrying", file=sys.stderr, flush=True)
                said_unreachable = True
        if time.monotonic() >= deadline:
            return None, why
        time.sleep(1)


def run_auto(client: Client, mode: str, count: int, timeout: float, pace: float = 0.0) -> int:
    for i in range(count):
        pair, why = wait_for_pair(client, timeout, quiet=True)
        if pair is None:
            print(f"error: no pair to label came within {timeout:g} s ({why}); "
                  f"{i} of {count} answered", file=sys.stderr)
            return 1
        choice = ALTERNATE[i % len(ALTERNATE)] if mode == "alternate" else mode
        # A person's pace: look at the pair this long before answering.
        time.sleep(pace)
        try:
            client.answer(pair["query"], choice, took_ms=pace * 1000,
                          deadline=time.monotonic() + timeout)
        except ApiError as e:
            print(f"error: the teacher refused the answer to query {pair['query']}: "
                  f"{e.message} (HTTP {e.status})", file=sys.stderr)
            return 1
        except Unreachable as e:
            print(f"error: {e}", file=sys.stderr)
            return 1
        print(f"answered query {pair['query']}: {choice}", flush=True)
    return 0


KEYS = {"a": "left", "b": "right", "=": "equal", "s": "skip"}


def run_interactive(client: Client) -> int:
    try:
        print(f"labelling as {client.name} at {client.base} {status_line(client.status())}")
    except (ApiError, Unreachable) as e:
        print(f"status: {e}", file=sys.stderr)
    while True:
        pair, _ = wait_for_pair(client, float("inf"), quiet=False)
        print()
        print(f"pair {pair.get('display', '?')}")
        print(describe(pair))
        shown = time.monotonic()
        while True:
            try:
                key = input("A better (a), B better (b), equal (=), can't tell (s), undo (u), quit (q)? ")
            except EOFError:
                print()
                return 0
            key = key.strip().lower()
            if key == "q":
                return 0
            if key == "u":
                try:
                    res = client.undo()
                    print("undone your last answer; that pair comes back next")
                    break  # the undone pair comes back from /next
                except ApiError as e:
                    print(f"teacher: {e.message}")
                except Unreachable as e:
                    print(f"{e}; undo not sent")
                continue
            choice = KEYS.get(key)
            if choice is None:
                print("please type a, b, =, s, u or q")
                continue
            try:
                res = client.answer(pair["query"], choice, (time.monotonic() - shown) * 1000)
                total = res.get("answered")
                # NOTE: the pair's display number, not the query id: a repeat shows
                # under a new one, so a person cannot tell a consistency check by it.
                print(f"answered pair {pair.get('display', '?')}: {choice}"
                      + (f" ({total} by {client.name} so far)" if total is not None else ""))
            except ApiError as e:
                print(f"teacher refused the answer: {e.message} (HTTP {e.status})")
            break


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description="Label pbrl preference pairs from a terminal (teacher API, protocol 1).")
    ap.add_argument("--url", default="http://127.0.0.1:8080", help="the teacher's address")
    ap.add_argument("--name", required=True, help="labeller name: 1-40 letters, digits, space, _ . -")
    ap.add_argument("--token", default=None, help="bearer token, if the teacher asks for one")
    ap.add_argument("--answer", choices=CHOICES + ("alternate",), default=None,
                    help="answer automatically (alternate cycles left, right, equal)")
    ap.add_argument("--count", type=int, default=1, help="with --answer: how many pairs to answer")
    ap.add_argument("--pace", type=float, default=0.0,
                    help="with --answer: seconds to wait on each pair before answering")
    ap.add_argument("--timeout", type=float, default=120.0,
                    help="with --answer: give up when no pair comes for this many seconds")
    args = ap.parse_args(argv)
    if not NAME_RE.match(args.name):
        ap.error("--name must be 1-40 letters, digits, space, _ . -")
    if args.count < 0:
        ap.error("--count must be >= 0")
    client = Client(args.url, args.name, args.token)
    try:
        if args.answer:
            if args.pace < 0:
                ap.error("--pace must be >= 0")
            return run_auto(client, args.answer, args.count, args.timeout, args.pace)
        return run_interactive(client)
    except ApiError as e:
        print(f"error: teacher said: {e.message} (HTTP {e.status})", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
