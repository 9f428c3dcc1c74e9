"""Many clients editing the same features at once, and a check that no update was lost.

Used by ``tests/test_concurrent_edits.py`` (a few seconds in CI) and by
``benchmarks/concurrent_edits.py`` (a minute, with figures).

Every write is an increment: a client reads a feature (its ``weight`` and
``ETag``) and writes ``weight + 1`` with a unique ``writer`` tag, conditioned
on the version it read:

* ``PATCH`` with ``If-Match`` (rejected: 412),
* ``PUT`` of the whole feature with ``If-Match`` (rejected: 412),
* a changeset updating two features, each with its expected version
  (rejected whole: 409).

A lost update shows as a final ``weight`` below the start plus the accepted
increments. :func:`verify` checks more than that: the history of each feature
is an unbroken chain (each edit starts from the previous edit's result), its
edits are exactly the writes the clients were told were accepted (with the
version each was answered), replaying them from the created feature gives the
final state, and every rejected write was answered 412 or 409.
"""

from __future__ import annotations

import random
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import httpx

#: What a rejected write may be answered with, per kind of write.
REJECTED = {"patch": 412, "put": 412, "changeset": 409}


@dataclass
class Accepted:
    feature: str
    version: int  # as answered to the client (ETag or changeset result)
    writer: str
    kind: str


@dataclass
class RaceResult:
    accepted: list[Accepted] = field(default_factory=list)
    #: (kind, HTTP status or exception name) -> count, for every write sent
    answers: dict[tuple[str, str], int] = field(default_factory=dict)
    seconds: float = 0.0

    def count(self, status: str) -> int:
        return sum(n for (_, s), n in self.answers.items() if s == status)

    @property
    def writes(self) -> int:
        return sum(self.answers.values())

    def unexpected(self) -> dict[tuple[str, str], int]:
        """Answers that are neither an acceptance nor the rejection that kind of write must get."""
        ok = {"patch": "200", "put": "200", "changeset": "201"}
        return {k: n for k, n in self.answers.items() if k[1] not in (ok[k[0]], str(REJECTED[k[0]]))}


def create_features(client: httpx.Client, map_id: str, n: int) -> list[str]:
    ids = []
    for k in range(n):
        f = {"type": "Feature", "geometry": {"type": "Point", "coordinates": [8.428 + k * 1e-4, 49.0071]},
             "properties": {"weight": 100.0, "kind": "dash", "writer": "create"}}  # fmt: skip
        r = client.post(f"/collections/{map_id}/items", json=f)
        assert r.status_code == 201, r.text
        ids.append(r.json()["id"])
    return ids


def _etag_version(r: httpx.Response) -> int:
    return int(r.headers["etag"].strip('"'))


def race(base_url: str, token: str, map_id: str, ids: list[str], *, clients: int = 20,
         duration: float = 60.0, seed: int = 0, think_s: float = 0.005,
         min_accepted: int = 0, max_duration: float | None = None) -> RaceResult:  # fmt: skip
    """``clients`` threads editing ``ids`` for ``duration`` seconds.

    With ``min_accepted`` the race goes on past ``duration`` (up to
    ``max_duration``, default four times ``duration``) until that many writes
    were accepted: on a loaded machine a fixed few seconds may hold too few
    writes to be a race at all.
    """
    result = RaceResult()
    lock = threading.Lock()
    auth = {"Authorization": f"Bearer {token}"}
    t0 = time.monotonic()
    deadline = t0 + duration
    hard_deadline = t0 + (max_duration if max_duration is not None else 4 * duration)

    def going() -> bool:
        now = time.monotonic()
        return now < deadline or (len(result.accepted) < min_accepted and now < hard_deadline)

    def note(kind: str, status: str, accepted: list[Accepted] = ()) -> None:
        with lock:
            result.answers[(kind, status)] = result.answers.get((kind, status), 0) + 1
            result.accepted.extend(accepted)

    def client_loop(k: int) -> None:
        rng = random.Random(seed * 1000 + k)
        seq = 0
        with httpx.Client(base_url=base_url, headers=auth, timeout=60.0) as c:
            while going():
                seq += 1
                tag = f"c{k}-{seq}"
                roll = rng.random()
                kind = "patch" if roll < 0.4 else "put" if roll < 0.7 else "changeset"
                picked = rng.sample(ids, 2 if kind == "changeset" else 1)
                current = {}
                for fid in picked:
                    r = c.get(f"/collections/{map_id}/items/{fid}")
                    assert r.status_code == 200, r.text
                    current[fid] = (r.json(), _etag_version(r))
                # a client thinks a little between reading and writing: more races
                time.sleep(rng.uniform(0, think_s))
                try:
                    if kind == "changeset":
                        changes = [{"op": "update", "id": fid, "version": str(v),
                                    "patch": {"properties": {"weight": f["properties"]["weight"] + 1,
                                                             "writer": tag}}}
                                   for fid, (f, v) in current.items()]  # fmt: skip
                        r = c.post(f"/collections/{map_id}/changesets", json={"comment": tag, "changes": changes})
                        got = [Accepted(x["id"], int(x["version"]), tag, kind) for x in r.json()["results"]] \
                            if r.status_code == 201 else []  # fmt: skip
                    else:
                        (fid, (f, v)), = current.items()
                        h = {"If-Match": f'"{v}"'}
                        if kind == "patch":
                            body = {"properties": {"weight": f["properties"]["weight"] + 1, "writer": tag}}
                            r = c.patch(f"/collections/{map_id}/items/{fid}", json=body,
                                        headers={**h, "Content-Type": "application/merge-patch+json"})  # fmt: skip
                        else:
                            props = {**f["properties"], "weight": f["properties"]["weight"] + 1, "writer": tag}
                            props.pop("version", None)
                            r = c.put(f"/collections/{map_id}/items/{fid}", headers=h,
                                      json={"type": "Feature", "geometry": f["geometry"], "properties": props})  # fmt: skip
                        got = [Accepted(fid, _etag_version(r), tag, kind)] if r.status_code == 200 else []
                except httpx.HTTPError as exc:
                    note(kind, type(exc).__name__)
                    continue
                note(kind, str(r.status_code), got)

    t0 = time.monotonic()
    with ThreadPoolExecutor(clients) as pool:
        for fut in [pool.submit(client_loop, k) for k in range(clients)]:
            fut.result()
    result.seconds = time.monotonic() - t0
    return result


def feature_history(client: httpx.Client, map_id: str, fid: str) -> list[dict]:
    """Every edit of one feature, oldest first."""
    edits, offset = [], 0
    while True:
        page = client.get(f"/collections/{map_id}/history",
                          params={"feature": fid, "limit": 1000, "offset": offset}).json()  # fmt: skip
        edits.extend(page["edits"])
        offset += page["numberReturned"]
        if not page["numberReturned"] or offset >= page["numberMatched"]:
            break
    return sorted(edits, key=lambda e: int(e["id"]))


def verify(base_url: str, map_id: str, ids: list[str], result: RaceResult) -> list[str]:
    """Every violation of the invariants in the module docstring; empty when none."""
    problems: list[str] = []
    for key, n in result.unexpected().items():
        problems.append(f"{n} {key[0]} write(s) answered {key[1]} (expected {REJECTED[key[0]]} when rejected)")
    by_feature: dict[str, dict[str, Accepted]] = {fid: {} for fid in ids}
    for a in result.accepted:
        by_feature[a.feature][a.writer] = a
    with httpx.Client(base_url=base_url, timeout=60.0) as c:
        for fid in ids:
            edits = feature_history(c, map_id, fid)
            if not edits or edits[0]["op"] != "create":
                problems.append(f"feature {fid}: history does not start with its creation")
                continue
            state = dict(edits[0]["after"])
            start_weight = state["weight"]
            seen: set[str] = set()
            for e in edits[1:]:
                before, after = e["before"], e["after"]
                if e["op"] != "update" or after is None:
                    problems.append(f"feature {fid}: unexpected {e['op']} edit {e['id']}")
                    continue
                if before["version"] != state["version"] or before["weight"] != state["weight"]:
                    problems.append(f"feature {fid}: edit {e['id']} starts from version {before['version']}, "
                                    f"weight {before['weight']}; the previous edit left {state['version']}, "
                                    f"{state['weight']} (broken chain)")  # fmt: skip
                writer = (after.get("extra") or {}).get("writer")
                acc = by_feature[fid].get(writer)
                if acc is None:
                    problems.append(f"feature {fid}: edit {e['id']} by {writer!r} is in the history, "
                                    "but its client was not told it was accepted")  # fmt: skip
                else:
                    seen.add(writer)
                    if acc.version != after["version"]:
                        problems.append(f"feature {fid}: {writer} was answered version {acc.version}, "
                                        f"its edit made version {after['version']}")  # fmt: skip
                # replay the client's intended change on the state it was based on
                state = {**state, "weight": state["weight"] + 1, "version": state["version"] + 1,
                         "extra": {**(state.get("extra") or {}), "writer": writer}}  # fmt: skip
                if after["weight"] != state["weight"] or after["version"] != state["version"]:
                    problems.append(f"feature {fid}: edit {e['id']} wrote weight {after['weight']} "
                                    f"version {after['version']}, replay gives {state['weight']} "
                                    f"{state['version']}")  # fmt: skip
            missing = set(by_feature[fid]) - seen
            if missing:
                problems.append(f"feature {fid}: {len(missing)} accepted write(s) are not in the history "
                                f"(lost updates), e.g. {sorted(missing)[:3]}")  # fmt: skip
            r = c.get(f"/collections/{map_id}/items/{fid}")
            final = r.json()["properties"]
            if (final["weight"], final["version"], final.get("writer")) != (
                    state["weight"], state["version"], state["extra"].get("writer")):  # fmt: skip
                problems.append(f"feature {fid}: final weight/version/writer {final['weight']}/"
                                f"{final['version']}/{final.get('writer')} differ from the replay "
                                f"{state['weight']}/{state['version']}/{state['extra'].get('writer')}")  # fmt: skip
            if final["weight"] != start_weight + len(by_feature[fid]):
                problems.append(f"feature {fid}: weight went from {start_weight} to {final['weight']} "
                                f"with {len(by_feature[fid])} accepted increments (lost update)")  # fmt: skip
    return problems
