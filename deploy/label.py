#!/usr/bin/env python3
"""Label pbrl preference pairs from a terminal.

A minimal client for the human teacher's HTTP/JSON API (protocol 1), standard library only.
The teacher serves the labelling page at `/` and this API beside it:

    GET  /api/v1/status?labeller=NAME              progress: open queries, answers, budget, ...
    GET  /api/v1/next?labeller=NAME[&exclude=ID]   200 with a pair or a ranking, or 204 when
                                                   nothing is open
    POST /api/v1/answer  {"labeller", "query", "choice", "took_ms", "replays"}
                         choice is "left" | "right" | "equal" | "skip"   -> {"ok": true, "answered": N}
                         a ranking: "places" (one per attempt as shown, 0 the best, ties
                         sharing a place) instead of the choice
    POST /api/v1/undo    {"labeller"}   withdraws this labeller's last answer -> {"query": ID};
                         409 {"error": "nothing to undo"} when there is none. The withdrawn
                         query comes back from the next /next call.

A pair is {"query", "display", "kind": "pair", "steps", "left": ATTEMPT, "right": ATTEMPT}; a
ranking is {"query", "display", "kind": "rank", "steps", "attempts": [ATTEMPT, ...]} (three or
four, in the order shown to this labeller); an attempt carries, per frame
(steps + 1 entries), world positions in metres (z up): frames.spoon, frames.mouth, frames.head,
frames.arm (joint origins, end effector, spoon) and frames.food (one point per particle), and
what a person would feel or see: readout.distance (spoon to mouth, m), readout.speed (m/s),
readout.force (on the person, N) and readout.food ([on the spoon, eaten, spilled, touched the
person] so far). Frames before segment_from are lead-in, shown but not judged.
Errors are 4xx with {"error": "message"}. With --token T every call carries
"Authorization: Bearer T".

Interactive (the default):
    python3 deploy/label.py --url http://127.0.0.1:8080 --name ana
prints what the page's strips show for each attempt over the judged part (closest and mean
distance to the mouth, mean and top spoon speed, peak and mean force on the person, food eaten,
spilled and on the person) with a sparkline of the distance, and asks a/b/=/s/u/q.

Non-interactive (tests):
    python3 deploy/label.py --url ... --name ana --answer alternate --count 5
answers 5 pairs (alternate cycles left, right, equal), one line each
("answered query 17: left"), and exits 0; exits 1 when no pair came for --timeout seconds. A
ranking is answered in the order shown for left, reversed for right, all tied for equal
("answered query 18: places [0, 1, 2]").
"""

from __future__ import annotations

import argparse
import http.client
import json
import re
import sys
import time
import urllib.error
import urllib.parse
import urllib.request

NAME_RE = re.compile(r"^[A-Za-z0-9 _.\-]{1,40}$")
CHOICES = ("left", "right", "equal", "skip")
ALTERNATE = ("left", "right", "equal")
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
        self.last_ms = 0.0  # the last successful call's round trip

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
        started = time.monotonic()
        try:
            with urllib.request.urlopen(req, timeout=HTTP_TIMEOUT_S) as res:
                status = res.status
                raw = res.read()
            self.last_ms = (time.monotonic() - started) * 1000
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

    def answer(self, query, choice, took_ms: int, deadline: float | None = None):
        """Posts an answer (a choice, or a ranking's places as a list), retrying while the
        teacher is unreachable (until `deadline`). A 409 for a retry means the earlier try
        got through: it counts as done."""
        body = {
            "labeller": self.name,
            "query": query,
            "took_ms": max(0, int(took_ms)),
            "replays": [0, 0],  # nothing is played back in a terminal
        }
        if isinstance(choice, list):
            body["places"] = choice
        else:
            body["choice"] = choice
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

SPARKS = "▁▂▃▄▅▆▇█"


def _mean(xs) -> float:
    return sum(xs) / len(xs) if xs else float("nan")


def summarise(attempt: dict) -> dict:
    """What the page's strips show, over the judged part of the clip (the frames after
    segment_from; the lead-in is not judged): distance to the mouth (closest, mean; m),
    spoon speed (mean, top; m/s), force on the person (peak, mean; N), and food eaten,
    spilled and on the person in that part, and left on the spoon at the end. Raises
    ValueError when the attempt has no readout (a teacher older than this client)."""
    r = attempt.get("readout") or {}
    distance, speed, force, food = (r.get(k) or [] for k in ("distance", "speed", "force", "food"))
    n = len(distance)
    if n == 0 or any(len(x) != n for x in (speed, force, food)):
        raise ValueError("the attempt has no readout (the teacher may be older than this client)")
    start = min(max(int(attempt.get("segment_from") or 0), 0), n - 1)
    # NOTE: frame k is the state after step k: the judged steps end at frames start+1...
    j = min(start + 1, n - 1)
    judged = slice(j, n)
    return {
        "closest": min(distance[judged]),
        "mean_distance": _mean(distance[judged]),
        "mean_speed": _mean(speed[judged]),
        "top_speed": max(speed[judged]),
        "peak_force": max(force[judged]),
        "mean_force": _mean(force[judged]),
        "eaten": food[-1][1] - food[start][1],
        "spilled": food[-1][2] - food[start][2],
        "hits": food[-1][3] - food[start][3],
        "left": food[-1][0],
        "distance": distance,
        "start": start,
    }


def sparkline(xs, top: float, width: int = 40) -> str:
    """`xs` in `width` characters, each the mean of its share of the frames, on 0..top."""
    if not xs:
        return ""
    out = []
    for i in range(width):
        a, b = i * len(xs) // width, max(i * len(xs) // width + 1, (i + 1) * len(xs) // width)
        v = _mean(xs[a:b]) / top if top > 0 else 0.0
        out.append(SPARKS[min(len(SPARKS) - 1, max(0, int(v * (len(SPARKS) - 1) + 0.5)))])
    return "".join(out)


def attempts_of(pair: dict) -> list:
    """(label, attempt) for each attempt shown: A and B of a pair, 1, 2, ... of a ranking."""
    if pair.get("kind") == "rank":
        return [(str(k + 1), a) for k, a in enumerate(pair.get("attempts") or [])]
    return [("A", pair.get("left")), ("B", pair.get("right"))]


def places_of(text: str, n: int):
    """A ranking typed best to worst ("2 3 1", ties joined by "=": "2=3 1") as each
    attempt's place in the order shown (0 the best), or None if it does not name each of
    the n attempts once."""
    groups = [g for g in text.replace(",", " ").split() if g]
    places, seen = [None] * n, 0
    for g in groups:
        members = g.split("=")
        if not all(m.isdigit() and 1 <= int(m) <= n for m in members):
            return None
        for m in members:
            if places[int(m) - 1] is not None:
                return None
            places[int(m) - 1] = seen
        seen += len(members)
    return places if None not in places else None


def describe(pair: dict) -> str:
    sides = []
    for label, attempt in attempts_of(pair):
        try:
            sides.append((label, summarise(attempt or {})))
        except ValueError as e:
            return f"pair of {pair.get('steps', '?')} steps: cannot summarise attempt {label}: {e}"
    top = max(max(s["distance"]) for _, s in sides)
    first = sides[0][1]
    lead = first["start"] * 40 // max(1, len(first["distance"]))
    rows = [f"pair of {pair.get('steps', '?')} steps; numbers over the judged part"
            + (f" (the sparkline's first {lead} marks are lead-in)" if lead else "") + ":"]
    for label, s in sides:
        rows.append(
            f"  {label}: distance to the mouth closest {s['closest'] * 100:.1f} cm, "
            f"mean {s['mean_distance'] * 100:.1f} cm  {sparkline(s['distance'], top)}\n"
            f"     spoon speed mean {s['mean_speed'] * 100:.1f}, top {s['top_speed'] * 100:.1f} cm/s; "
            f"force on the person peak {s['peak_force']:.2f}, mean {s['mean_force']:.2f} N\n"
            f"     food eaten {s['eaten']}, spilled {s['spilled']}, on the person {s['hits']}; "
            f"{s['left']} left on the spoon at the end"
        )
    return "\n".join(rows)


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


def run_auto(client: Client, mode: str, count: int, timeout: float, pace: float = 0.0,
             timing: bool = False) -> int:
    for i in range(count):
        started = time.monotonic()
        pair, why = wait_for_pair(client, timeout, quiet=True)
        if timing and pair is not None:
            # The last /next call's round trip: what serving a pair costs (the wait for
            # the learner's queries before it is not counted).
            print(f"served query {pair['query']} in {client.last_ms:.0f} ms "
                  f"({(time.monotonic() - started) * 1000:.0f} ms with waiting)", flush=True)
        if pair is None:
            print(f"error: no pair to label came within {timeout:g} s ({why}); "
                  f"{i} of {count} answered", file=sys.stderr)
            return 1
        choice = ALTERNATE[i % len(ALTERNATE)] if mode == "alternate" else mode
        if pair.get("kind") == "rank" and choice != "skip":
            n = len(pair.get("attempts") or [])
            choice = {"left": list(range(n)), "right": list(range(n))[::-1],
                      "equal": [0] * n}[choice]
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
        said = f"places {choice}" if isinstance(choice, list) else choice
        print(f"answered query {pair['query']}: {said}", flush=True)
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
        ranking = pair.get("kind") == "rank"
        n = len(pair.get("attempts") or [])
        while True:
            try:
                key = input(f"rank {', '.join(str(k + 1) for k in range(n))} best to worst "
                            "(e.g. '2 3 1', ties '2=3 1'), can't tell (s), undo (u), quit (q)? "
                            if ranking else
                            "A better (a), B better (b), equal (=), can't tell (s), undo (u), quit (q)? ")
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
            choice = KEYS.get(key) if not ranking or key == "s" else places_of(key, n)
            if choice is None:
                print(f"please name each of the {n} attempts once, best first (or s, u, q)"
                      if ranking else "please type a, b, =, s, u or q")
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
        description="Label pbrl preference pairs from a terminal (teacher API, protocol 1). "
        "By default it is interactive: for each pair it prints what the labelling page's "
        "strips show for attempts A and B (distance to the mouth, spoon speed, force on "
        "the person, food eaten and spilled, over the part to judge) and asks which is "
        "better (a, b, = for equal, s for can't tell, u to undo the last answer, q to quit). "
        "With --answer it answers --count pairs by itself (for tests and demos).")
    ap.add_argument("--url", default="http://127.0.0.1:8080", help="the teacher's address")
    ap.add_argument("--name", required=True, help="labeller name: 1-40 letters, digits, space, _ . -")
    ap.add_argument("--token", default=None, help="bearer token, if the teacher asks for one")
    ap.add_argument("--answer", choices=CHOICES + ("alternate",), default=None,
                    help="answer automatically (alternate cycles left, right, equal)")
    ap.add_argument("--count", type=int, default=1, help="with --answer: how many pairs to answer")
    ap.add_argument("--pace", type=float, default=0.0,
                    help="with --answer: seconds to wait on each pair before answering")
    ap.add_argument("--timing", action="store_true",
                    help="with --answer: print how long each pair took to serve")
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
            return run_auto(client, args.answer, args.count, args.timeout, args.pace,
                            args.timing)
        return run_interactive(client)
    except ApiError as e:
        print(f"error: teacher said: {e.message} (HTTP {e.status})", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
