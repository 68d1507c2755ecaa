"""The cluster suite (issue #17): etcd x3, PostgreSQL + Patroni x3, loopd x3 in cluster mode and
HAProxy in containers (docker/cluster/compose.yaml), with the faults a fleet meets under a bounded
load of real descriptors (corridor, embedded once by the cluster). After every fault it asserts:
every acknowledged frame is stored exactly once and survives; errors come only for calls that were
never acknowledged; never two writable primaries; no answer holds a frame missing afterwards.
Run by docker/cluster/test; prints one line per check, then a table of what it measured.
`suite.py T2 T4` runs the cluster's start and the embedding, then only the checks named (CHECKS)."""
from __future__ import annotations

import io
import json
import os
import pathlib
import random
import statistics
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
import urllib.error
import urllib.request

import grpc

from loopd_client import NO_RETRY, Client, Frame, RetryPolicy, pb

ROOT = pathlib.Path(__file__).resolve().parents[2]
DATA = pathlib.Path(os.environ.get("LOOPD_SHARED_DATA", ROOT.parent / "shared/data")).resolve()
PROJECT = "loopdcluster"
ADMIN = "admin-key-for-the-cluster-suite-0123456789"
FIGURES = os.environ.get("LOOPD_CLUSTER_FIGURES") == "1"
PG = ("pg1", "pg2", "pg3")
NODES = ("loopd1", "loopd2", "loopd3")
PATRONI = ["patronictl", "-c", "/etc/loopd-cluster/patroni.yml"]
figures: list[tuple[str, str]] = []
# The checks that can be run alone (the start and the embedding always run: the rest needs them).
CHECKS = ("T6", "T5", "members", "jobs", "latency", "throughput", "T1", "T3", "T2", "T4", "T4b", "T4c", "T7", "T8",
          "primary", "robot")
selected: set[str] = set()
# Checks run only when named, not in CI's whole run (none now: T4c, opt-in while its write gap was
# over 30 s, runs since the connection fixes of docs/cluster.md).
OPT_IN: set[str] = set()


def sh(*args, check=True, env=None, timeout=120) -> str:
    r = subprocess.run(list(args), capture_output=True, text=True, env=env, timeout=timeout)
    if check and r.returncode != 0:
        raise AssertionError(f"{' '.join(args)} failed ({r.returncode}): {r.stderr.strip()[-2000:]}")
    return (r.stdout or "").strip()


def check(name, key: str | None = None):
    def run(f):
        if key and ((selected and key not in selected) or (not selected and key in OPT_IN)):
            print(f"skip {name}", flush=True)
            return
        start = time.monotonic()
        f()
        print(f"ok   {name} ({time.monotonic() - start:.1f} s)", flush=True)
    return run


def until(what: str, probe, timeout: float, every: float = 0.5):
    """probe()'s first truthy answer within `timeout` seconds."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            last = probe()
            if last:
                return last
        except Exception as e:  # noqa: BLE001 (a container between states answers anything)
            last = e
        time.sleep(every)
    raise AssertionError(f"{what}: not within {timeout} s (last: {last!r})")


class Cluster:
    def __init__(self, work: pathlib.Path):
        key = work / "admin.key"
        key.write_text(ADMIN)
        key.chmod(0o644)
        out = work / "out"
        out.mkdir()
        out.chmod(0o777)  # the robot runs as an unprivileged user
        self.env = dict(os.environ, LOOPD_ADMIN_KEY_PATH=str(key), LOOPD_SHARED_DATA=str(DATA),
                        LOOPD_TEST_OUT=str(out))
        self.key = ""
        self.sled_key = ""  # the sled loopd keeps its own tenants
        self.ips: dict[str, str] = {}
        self.unanswering: set[str] = set()
        # Servers frozen with `docker pause` (T4c): never `docker exec` into one. runc's exec into
        # a frozen container hangs and holds the daemon's lock on it, so `docker unpause` (and
        # every later command on it) hung too; a timeout kills only the client.
        self.paused: set[str] = set()

    def compose(self, *args, check=True) -> str:
        return sh("docker-compose", "-p", PROJECT, "-f", str(ROOT / "docker/cluster/compose.yaml"), *args,
                  check=check, env=self.env, timeout=300)

    def container(self, service: str) -> str:
        return f"{PROJECT}_{service}_1"

    def addr(self, service: str, port: int) -> str:
        """host:port of a container on the front network, reached from here through its bridge (a
        published port would follow the network it was published on, and a fault may cut that)."""
        if service not in self.ips:
            self.ips[service] = sh("docker", "inspect", "-f",
                                   f'{{{{(index .NetworkSettings.Networks "{PROJECT}_front").IPAddress}}}}',
                                   self.container(service))
        return f"{self.ips[service]}:{port}"

    def grpc(self, service: str = "lb", retry=NO_RETRY, timeout: float = 20) -> Client:
        key = self.sled_key if service == "sled" else self.key
        return Client(self.addr(service, 50051), key=key, retry=retry, timeout=timeout)

    def http(self, method: str, path: str, body=None, service: str = "lb", key=None):
        request = urllib.request.Request(
            f"http://{self.addr(service, 8080)}{path}", method=method,
            data=None if body is None else json.dumps(body).encode(),
            headers={"Authorization": f"Bearer {key or self.key}", "Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=30) as r:
            return r.status, dict(r.headers), json.loads(r.read() or b"null")

    # PostgreSQL, seen from inside its containers (the ground truth, not through loopd).
    def members(self) -> list[dict]:
        """Patroni's member list, as the first server that can reach etcd tells it (a server cut
        off from etcd cannot: it is asked last next time)."""
        for pg in sorted(PG, key=lambda p: p in self.unanswering):
            if pg in self.paused:
                continue
            try:
                out = sh("docker", "exec", self.container(pg), *PATRONI, "list", "-f", "json", check=False, timeout=8)
            except subprocess.TimeoutExpired:
                out = ""
            if out.startswith("["):
                self.unanswering.discard(pg)
                return json.loads(out)
            self.unanswering.add(pg)
        return []

    def leader(self) -> str:
        return next((m["Member"] for m in self.members() if m["Role"] == "Leader" and m["State"] == "running"), "")

    def leader_other_than(self, old: str) -> str:
        leader = self.leader()
        return "" if leader == old else leader

    def healthy(self) -> bool:
        """A leader and two streaming standbys, one of them synchronous."""
        m = self.members()
        roles = sorted(x["Role"] for x in m if x["State"] in ("running", "streaming"))
        return len(m) == 3 and roles.count("Leader") == 1 and "Sync Standby" in roles and len(roles) == 3

    def sql(self, pg: str, query: str, timeout: float = 10) -> str:
        return sh("docker", "exec", "-e", "PGPASSWORD=postgres-test-only", "-e", "PGCONNECT_TIMEOUT=3",
                  self.container(pg), "psql", "-h", "127.0.0.1", "-U", "postgres", "-d", "loopd", "-tAXc", query,
                  timeout=timeout)

    def not_writable(self, pg: str) -> bool:
        """In recovery, or not answering (down, starting, restarting, cut off): not writable. Asked
        inside its container, so a network cut does not stop the question. A frozen one takes
        no writes (and is not asked)."""
        if pg in self.paused:
            return True
        try:
            return self.sql(pg, "SELECT pg_is_in_recovery()", timeout=5) != "f"
        except Exception:  # noqa: BLE001
            return True

    def writable(self) -> list[str]:
        """The PostgreSQL servers that are up and not in recovery now."""
        out: list[str] = []

        def ask(pg):
            if not self.not_writable(pg):
                out.append(pg)
        threads = [threading.Thread(target=ask, args=(pg,)) for pg in PG]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return out

    def stored(self, session: str) -> list[int]:
        """Frame ids of a session as the current primary holds them (with repeats, if any)."""
        pg = until("a primary", self.leader, 60)
        # The store's id is the tenant's name, '/', the session's id.
        tbl = self.sql(pg, f"SELECT tbl FROM loopd_sessions WHERE id = 'fleet/{session}'")
        assert tbl, f"session {session} is not in the log"
        return [int(x) for x in self.sql(pg, f"SELECT frame_id FROM loopd_frames_{tbl}").split()]

    def wait_node(self, service: str, timeout: float = 240) -> None:
        c = self.container(service)
        self.ips.pop(service, None)  # a restarted container may have another address

        def ready():
            state = sh("docker", "inspect", "-f", "{{.State.Status}} {{.State.Health.Status}}", c)
            if state.startswith("exited"):
                raise AssertionError(f"{c} exited: {logs(c)[-3000:]}")
            return state == "running healthy"
        try:
            until(f"{c} healthy", ready, timeout)
        except AssertionError as e:
            # What the node said: its state, its last health probes and its own last lines.
            state = sh("docker", "inspect", "-f", "{{.State.Status}} restarts={{.RestartCount}} "
                       "{{json .State.Health.Log}}", c, check=False)
            raise AssertionError(f"{e}\n{c}: {state[-2000:]}\n{c}'s log:\n{logs(c)[-4000:]}") from None

    def balanced(self, column: str = "status") -> dict[str, str]:
        """HAProxy's view, backend/server -> a column of its stats (status: UP, DOWN, ...)."""
        with urllib.request.urlopen(f"http://{self.addr('lb', 8404)}/stats;csv", timeout=5) as r:
            rows = r.read().decode().lstrip("# ").splitlines()
        head = rows[0].split(",")
        return {f"{row['pxname']}/{row['svname']}": row[column]
                for row in (dict(zip(head, line.split(","))) for line in rows[1:])
                if row["svname"] not in ("FRONTEND", "BACKEND")}


def logs(container: str) -> str:
    r = subprocess.run(["docker", "logs", container], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return r.stdout


class Load:
    """Bounded load through the balancer while a fault happens: one writer storing frames with
    ids (each tried again until stored), one writer storing frames with server-assigned ids in
    a session of its own (the client's retries carry the frame's idempotency key, issue #34), one
    querier. Records what was acknowledged, every error and every frame id any answer held."""

    def __init__(self, cluster: Cluster, session: str, descriptors: list[list[float]], rate: float = 25):
        self.cluster, self.session, self.descriptors, self.rate = cluster, session, descriptors, rate
        self.acked: list[int] = []  # ids whose call answered OK
        self.ack_times: list[float] = []
        self.stored_by_lost_call: list[int] = []  # ALREADY_EXISTS on a retry: an unanswered call stored it
        self.errors: dict[str, int] = {}
        self.answered: set[int] = set()
        self.stale_answers = 0
        self.stop = threading.Event()
        self.next_id = 0
        self.keyed_session = f"{session}-keyed"
        self.keyed_acked = 0  # server-id writes acknowledged (after the client's retries)
        self.keyed_unknown = 0  # server-id writes whose retries ran out: stored or not
        self.threads = [threading.Thread(target=self.write), threading.Thread(target=self.query),
                        threading.Thread(target=self.keyed_write)]

    def __enter__(self):
        with self.cluster.grpc() as c:
            c.create_session(self.keyed_session)
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        for t in self.threads:
            t.join()

    def error(self, e: grpc.RpcError) -> None:
        name = e.code().name
        self.errors[name] = self.errors.get(name, 0) + 1

    def write(self) -> None:
        with self.cluster.grpc() as c:
            tried = False
            while not self.stop.is_set():
                i = self.next_id
                d = self.descriptors[i % len(self.descriptors)]
                try:
                    c.add_frame(self.session, "writer", Frame(descriptor=d, frame_id=i, timestamp=float(i)))
                    self.acked.append(i)
                    self.ack_times.append(time.monotonic())
                    self.next_id, tried = i + 1, False
                except grpc.RpcError as e:
                    if e.code() == grpc.StatusCode.ALREADY_EXISTS and tried:
                        self.stored_by_lost_call.append(i)
                        self.next_id, tried = i + 1, False
                    else:
                        self.error(e)
                        tried = True
                        time.sleep(0.1)
                self.stop.wait(1 / self.rate)

    def keyed_write(self) -> None:
        """Server-assigned ids, each write retried by the client (after UNAVAILABLE and after its
        5 s deadline) with the idempotency key it sends by default."""
        with self.cluster.grpc(retry=RetryPolicy(deadline=60), timeout=5) as c:
            i = 0
            while not self.stop.is_set():
                d = self.descriptors[i % len(self.descriptors)]
                try:
                    c.add_frame(self.keyed_session, "keyed", Frame(descriptor=d, timestamp=float(i)))
                    self.keyed_acked += 1
                except grpc.RpcError as e:
                    self.error(e)
                    self.keyed_unknown += 1
                i += 1
                self.stop.wait(1 / self.rate)

    def query(self) -> None:
        with self.cluster.grpc() as c:
            while not self.stop.is_set():
                if self.acked:
                    d = self.descriptors[random.choice(self.acked) % len(self.descriptors)]
                    try:
                        for m in c.query(self.session, "querier", descriptor=d):
                            self.answered.add(m.frame_id)
                    except grpc.RpcError as e:
                        self.error(e)
                self.stop.wait(1 / self.rate)

    def gap(self, since: float) -> float:
        """The longest time between two acknowledgements after `since`."""
        times = [since] + [t for t in self.ack_times if t >= since]
        return max(b - a for a, b in zip(times, times[1:])) if len(times) > 1 else float("inf")

    def verify(self, cluster: Cluster, what: str) -> None:
        """The assertions every fault ends with."""
        stored = cluster.stored(self.session)
        assert len(stored) == len(set(stored)), f"{what}: a frame stored twice"
        missing = set(self.acked) - set(stored)
        assert not missing, f"{what}: acknowledged frames missing after the fault: {sorted(missing)[:20]}"
        assert set(self.stored_by_lost_call) <= set(stored), what
        # Ids written in order: only the one call in flight when the run stopped may be unknown.
        unknown = set(stored) - set(self.acked) - set(self.stored_by_lost_call)
        assert unknown <= {self.next_id}, f"{what}: frames stored that no call tried: {sorted(unknown)[:20]}"
        phantom = self.answered - set(stored)
        assert not phantom, f"{what}: answers held frames that are not stored: {sorted(phantom)[:20]}"
        unexpected = set(self.errors) - {"UNAVAILABLE", "DEADLINE_EXCEEDED", "CANCELLED"}
        assert not unexpected, f"{what}: errors other than 'not now': {self.errors}"
        # Server-assigned ids: every acknowledged write stored, none twice (a retry that stored
        # its frame again would count beyond what was sent).
        keyed = len(cluster.stored(self.keyed_session))
        sent = self.keyed_acked + self.keyed_unknown
        assert self.keyed_acked <= keyed <= sent, \
            f"{what}: {keyed} frames stored for {self.keyed_acked} acknowledged of {sent} keyed writes"


def main() -> None:
    unknown = set(sys.argv[1:]) - set(CHECKS)
    if unknown:
        sys.exit(f"unknown checks {sorted(unknown)}; the checks are {', '.join(CHECKS)}")
    selected.update(sys.argv[1:])
    with tempfile.TemporaryDirectory(prefix="loopd-cluster-") as work:
        os.chmod(work, 0o755)
        cluster = Cluster(pathlib.Path(work))
        cluster.compose("down", "-v", "--remove-orphans", check=False)
        try:
            run_checks(cluster)
        except BaseException:
            for c in ("lb", *NODES, *PG):
                print(f"--- {c}\n{logs(cluster.container(c))[-2500:]}", file=sys.stderr)
            raise
        finally:
            cluster.compose("down", "-v", "--remove-orphans", check=False)
    print("\n| measure | value |\n|---|---|")
    for what, value in figures:
        print(f"| {what} | {value} |")


def run_checks(cluster: Cluster) -> None:  # noqa: C901 (one story, told in order)
    watch = PrimaryWatch(cluster)

    @check("etcd x3 and PostgreSQL + Patroni x3 elect a primary with a synchronous standby")
    def _():
        start = time.monotonic()
        cluster.compose("up", "-d", "etcd1", "etcd2", "etcd3", "pg1", "pg2", "pg3")
        until("a Patroni leader and a synchronous standby", cluster.healthy, 180, every=1)
        figures.append(("database cluster up (3 etcd, 3 PostgreSQL), s", f"{time.monotonic() - start:.1f}"))
        watch.start()

    @check("loopd x3 (cluster mode), a sled loopd and HAProxy start; keys work through the balancer")
    def _():
        start = time.monotonic()
        cluster.compose("up", "-d", *NODES, "sled", "lb")
        for s in (*NODES, "sled"):
            cluster.wait_node(s)
        figures.append(("loopd nodes healthy after start (model loaded), s", f"{time.monotonic() - start:.1f}"))
        until("every node UP in the balancer",
              lambda: all(v == "UP" for k, v in cluster.balanced().items() if k.split("/")[0].endswith("ready")), 30)
        _, _, body = cluster.http("POST", "/v1/tenants", {"name": "fleet"}, key=ADMIN)
        cluster.key = body["key"]
        cluster.sled_key = cluster.http("POST", "/v1/tenants", {"name": "fleet"}, service="sled", key=ADMIN)[2]["key"]
        # The key was issued through one node; every node takes it (tenants live in the log).
        for node in NODES:
            until(f"{node} knows the key", lambda n=node: cluster.http("GET", "/v1/sessions", service=n)[0] == 200, 10)
        try:
            cluster.http("GET", "/v1/sessions", key="not-a-key")
            raise AssertionError("a bad key was accepted")
        except urllib.error.HTTPError as e:
            assert e.code == 401, e.code

    # CI embeds 60 + 60 (every check holds with them); LOOPD_CLUSTER_FIGURES=1 takes all 222 and
    # measures throughput too (docs/cluster.md's figures).
    per_side = None if FIGURES else 60
    corridor = sorted((DATA / "corridor/ref").glob("*.jpg"))[:per_side] \
        + sorted((DATA / "corridor/query").glob("*.jpg"))[:per_side]
    descriptors: list[list[float]] = []

    @check(f"the cluster embeds the corridor's {len(corridor)} images through the balancer (every node takes calls)")
    def _():
        start = time.monotonic()
        lb = cluster.addr("lb", 8080)
        for path in corridor:
            request = urllib.request.Request(f"http://{lb}/v1/embed", data=path.read_bytes(), headers={
                "Authorization": f"Bearer {cluster.key}", "Content-Type": "application/octet-stream"})
            with urllib.request.urlopen(request, timeout=60) as r:
                descriptors.append(json.load(r)["descriptor"])
        figures.append((f"embedding {len(corridor)} images through the balancer (CPU, 3 nodes), images/s",
                        f"{len(corridor) / (time.monotonic() - start):.1f}"))
        served = {k: int(v) for k, v in cluster.balanced("stot").items() if k.startswith("http_ready/")}
        assert sum(1 for v in served.values() if v > 0) == 3, f"calls per node: {served}"

    @check("T6 one sequence, cluster (through the balancer) and sled loopd: identical top-10 ids, order, scores", "T6")
    def _():
        refs, queries = descriptors[:len(descriptors) // 2], descriptors[len(descriptors) // 2:]
        answers = {}
        for target in ("lb", "sled"):
            with cluster.grpc(target, retry=None) as c:
                c.create_session("exact")
                for i, d in enumerate(refs):
                    c.add_frame("exact", "mapper", Frame(descriptor=d, frame_id=i, timestamp=float(i)))
                answers[target] = [[(m.frame_id, round(m.score, 6)) for m in c.query("exact", "visitor", descriptor=d)]
                                   for d in queries]
        assert answers["lb"] == answers["sled"], "the cluster ranks differently from sled"
        assert all(len(a) > 0 for a in answers["lb"])

    @check("T5 read-after-ack: write through node A, read and query through node B, 1,000 times", "T5")
    def _():
        with cluster.grpc("loopd1", retry=None) as c:
            c.create_session("raa")
        clients = [cluster.grpc(n, retry=None) for n in NODES]
        for i in range(1000):
            a, b = i % 3, (i + 1) % 3
            d = descriptors[i % len(descriptors)]
            clients[a].add_frame("raa", "r", Frame(descriptor=d, frame_id=i, timestamp=float(i)))
            try:
                status, _, frame = cluster.http("GET", f"/v1/sessions/raa/frames/{i}", service=NODES[b])
            except urllib.error.HTTPError as e:
                raise AssertionError(f"{NODES[b]} answered {e.code} for frame {i}, just acknowledged by {NODES[a]}")
            assert status == 200 and frame["frame_id"] == i, frame
            top = clients[b].query("raa", "q", descriptor=d, options=None)
            assert i in {m.frame_id for m in top if m.score > 0.9999} or len(top) >= 5 and top[4].score > 0.9999, \
                f"{NODES[b]} did not rank frame {i}, just acknowledged by {NODES[a]}: {top}"
        for c in clients:
            c.close()

    @check("members: each session owned and held warm by two of the three nodes (GET /v1/cluster)", "members")
    def _():
        sessions = set(cluster.sql(until("a primary", cluster.leader, 60), "SELECT id FROM loopd_sessions").split())

        def two_owners():
            views = [cluster.http("GET", "/v1/cluster", service=n, key=ADMIN)[2] for n in NODES]
            owned = [h["session"] for v in views for h in v["held"] if h["owner"]]
            assert all(v["members"] == [f"{n}:50051" for n in NODES] for v in views) \
                and sorted(owned) == sorted(list(sessions) * 2), f"sessions {sessions}, views {views}"
            return True
        until("two owners per session", two_owners, 20)

    @check("a sequence job started through the balancer is polled through it, and every node answers for it", "jobs")
    def _():
        cluster.http("POST", "/v1/sessions", {"id": "desk-job"})
        tar = io.BytesIO()
        with tarfile.open(fileobj=tar, mode="w") as t:
            for i in range(1, 11):
                t.add(DATA / f"slambook2-ch11/{i}.png", arcname=f"{i}.png")
        request = urllib.request.Request(
            f"http://{cluster.addr('lb', 8080)}/v1/sessions/desk-job/sequences", data=tar.getvalue(),
            headers={"Authorization": f"Bearer {cluster.key}", "Content-Type": "application/octet-stream"})
        with urllib.request.urlopen(request, timeout=60) as r:
            job = json.load(r)["job_id"]
        # Each poll may reach another node (HAProxy balances per call).
        status = until(f"{job} done", lambda: (lambda st: st if st["state"] != "running" else None)(
            cluster.http("GET", f"/v1/jobs/{job}")[2]), 120)
        assert status["state"] == "done" and status["done"] == 10 and not status["errors"], status
        tenth = [l["match_name"] for l in status["loops"] if l["query_name"] == "10.png"]
        assert tenth == ["1.png"], status["loops"]
        for node in NODES:
            assert cluster.http("GET", f"/v1/jobs/{job}", service=node)[2] == status, node

    @check("query latency through the balancer against a node directly (same session, same queries)", "latency")
    def _():
        for target in ("loopd1", "lb"):
            with cluster.grpc(target, retry=None) as c:
                times = []
                for i in range(400):
                    t = time.perf_counter()
                    c.query("raa", "q", descriptor=descriptors[i % len(descriptors)])
                    times.append((time.perf_counter() - t) * 1000)
            times.sort()
            figures.append((f"query p50 / p99 ms, 1,000 frames, {'through HAProxy' if target == 'lb' else 'one node directly'}",
                            f"{statistics.median(times):.2f} / {times[int(0.99 * len(times))]:.2f}"))

    @check("throughput side by side: durable frames/s and embedding, the cluster against one node", "throughput")
    def _():
        if not FIGURES:
            print("     skipped (LOOPD_CLUSTER_FIGURES=1 measures it)", flush=True)
            return
        def writes(target: str, session: str, threads: int = 8, per_thread: int = 150) -> float:
            with cluster.grpc(target, retry=None) as c:
                c.create_session(session)

            def run(t):
                with cluster.grpc(target, retry=None) as c:
                    for i in range(per_thread):
                        c.add_frame(session, f"w{t}", Frame(descriptor=descriptors[(t * per_thread + i) % len(descriptors)],
                                                           frame_id=t * per_thread + i, timestamp=float(i)))
            start = time.monotonic()
            pool = [threading.Thread(target=run, args=(t,)) for t in range(threads)]
            for t in pool:
                t.start()
            for t in pool:
                t.join()
            return threads * per_thread / (time.monotonic() - start)

        def embeds(target: str, threads: int = 3, images: int = 48) -> float:
            addr = cluster.addr(target, 8080)

            def run(t):
                for path in corridor[t::threads][:images // threads]:
                    request = urllib.request.Request(f"http://{addr}/v1/embed", data=path.read_bytes(),
                                                     headers={"Authorization": f"Bearer {cluster.key}"})
                    urllib.request.urlopen(request, timeout=60).read()
            start = time.monotonic()
            pool = [threading.Thread(target=run, args=(t,)) for t in range(threads)]
            for t in pool:
                t.start()
            for t in pool:
                t.join()
            return images / (time.monotonic() - start)

        cluster_rate, sled_rate = writes("lb", "rate-cluster"), writes("sled", "rate-sled")
        figures.append(("durable frames/s, 8 clients x 1 frame per call: cluster through HAProxy / one sled node",
                        f"{cluster_rate:.0f} / {sled_rate:.0f} ({cluster_rate / sled_rate:.2f})"))
        three, one = embeds("lb"), embeds("loopd1")
        figures.append(("images embedded/s, 3 clients: 3 nodes through HAProxy / 1 node (CPU, one 2-core machine)",
                        f"{three:.2f} / {one:.2f} ({three / one:.2f})"))

    @check("T1 a loopd node killed (SIGKILL) under load: the balancer routes around it", "T1")
    def _():
        with cluster.grpc() as c:
            c.create_session("t1")
        with Load(cluster, "t1", descriptors) as load:
            time.sleep(4)
            killed = time.monotonic()
            sh("docker", "kill", "-s", "KILL", cluster.container("loopd2"))
            time.sleep(8)
            gap = load.gap(killed)
        load.verify(cluster, "T1")
        assert gap < 5, f"writes stalled {gap:.1f} s after a node died"
        # Its sessions were owned by two of three members; after the member ttl (5 s) the two
        # left own and hold every session, loaded without a request.
        sessions = set(cluster.sql(until("a primary", cluster.leader, 60), "SELECT id FROM loopd_sessions").split())
        survivors = ("loopd1", "loopd3")

        def taken_over():
            views = [cluster.http("GET", "/v1/cluster", service=n, key=ADMIN)[2] for n in survivors]
            assert all(v["members"] == ["loopd1:50051", "loopd3:50051"]
                       and {h["session"] for h in v["held"] if h["owner"]} == sessions for v in views), \
                f"sessions {sessions}, views {views}"
            return True
        until("loopd1 and loopd3 own and hold every session", taken_over, 20)
        figures.append(("longest write gap after a loopd node is killed, s", f"{gap:.2f}"))
        cluster.compose("start", "loopd2")
        cluster.wait_node("loopd2")
        print(f"     {len(load.acked)} acknowledged, errors {load.errors}", flush=True)

    @check("T3 a loopd node cut off from the database: not ready, acknowledges nothing, catches up after", "T3")
    def _():
        with cluster.grpc() as c:
            c.create_session("t3")
        network = f"{PROJECT}_data"
        with Load(cluster, "t3", descriptors) as load:
            time.sleep(3)
            sh("docker", "network", "disconnect", network, cluster.container("loopd1"))
            until("loopd1 out of the balancer", lambda: cluster.balanced()["grpc_ready/loopd1"].startswith("DOWN"), 20)
            with cluster.grpc("loopd1") as cut:
                try:
                    cut.add_frame("t3", "cut", Frame(descriptor=descriptors[0], frame_id=10**9))
                    raise AssertionError("a node cut off from the database acknowledged a write")
                except grpc.RpcError as e:
                    assert e.code() == grpc.StatusCode.UNAVAILABLE and "database" in e.details(), e
                answer, call = cut._stub.Query.with_call(query_request("t3", descriptors[1]), metadata=cut._metadata,
                                                          timeout=30)
                assert ("loopd-stale", "1") in call.trailing_metadata() or ("loopd-stale", "1") in call.initial_metadata()
            time.sleep(3)
            sh("docker", "network", "connect", "--alias", "loopd1", network, cluster.container("loopd1"))
            until("loopd1 back in the balancer", lambda: cluster.balanced()["grpc_ready/loopd1"] == "UP", 30)
            time.sleep(2)
        load.verify(cluster, "T3")
        with cluster.grpc("loopd1") as back:
            last = load.acked[-1]
            top = back.query("t3", "q", descriptor=descriptors[last % len(descriptors)])
            assert any(m.frame_id == last for m in top) or top[0].score > 0.9999, top
            status, _, frame = cluster.http("GET", f"/v1/sessions/t3/frames/{last}", service="loopd1")
            assert status == 200, frame
        print(f"     {len(load.acked)} acknowledged, errors {load.errors}", flush=True)

    @check("T2 the PostgreSQL primary killed under load: Patroni promotes the synchronous standby", "T2")
    def _():
        with cluster.grpc() as c:
            c.create_session("t2")
        old = cluster.leader()
        with Load(cluster, "t2", descriptors) as load:
            time.sleep(4)
            killed = time.monotonic()
            sh("docker", "kill", "-s", "KILL", cluster.container(old))
            new = until("a new leader", lambda: cluster.leader_other_than(old), 60)
            until("writes acknowledged again", lambda: load.ack_times and load.ack_times[-1] > killed + 0.5, 60)
            time.sleep(3)
            gap = load.gap(killed)
        load.verify(cluster, "T2 after failover")
        figures.append(("write gap while Patroni replaces a killed primary (ttl 10 s), s", f"{gap:.1f}"))
        cluster.compose("start", old)
        until("the old primary back as a standby", cluster.healthy, 120, every=1)
        load.verify(cluster, "T2 after the old primary rejoined")
        print(f"     {old} -> {new}; {len(load.acked)} acknowledged, errors {load.errors}, gap {gap:.1f} s",
              flush=True)

    @check("T4 the primary cut off from etcd and its standbys (loopd still reaches it): one primary, no loss", "T4")
    def _():
        with cluster.grpc() as c:
            c.create_session("t4")
        old = cluster.leader()
        network = f"{PROJECT}_repl"
        with Load(cluster, "t4", descriptors) as load:
            time.sleep(4)
            cut = time.monotonic()
            sh("docker", "network", "disconnect", network, cluster.container(old))
            new = until("a new leader", lambda: cluster.leader_other_than(old), 90)
            until("writes acknowledged again", lambda: load.ack_times and load.ack_times[-1] > cut + 0.5, 90)
            time.sleep(3)
            gap = load.gap(cut)
        load.verify(cluster, "T4 during the cut")
        figures.append(("write gap while the primary is cut off from etcd and standbys, s", f"{gap:.1f}"))
        sh("docker", "network", "connect", "--alias", f"{old}-repl", network, cluster.container(old))
        until("the old primary back as a standby", cluster.healthy, 120, every=1)
        load.verify(cluster, "T4 after it rejoined")
        print(f"     {old} -> {new}; {len(load.acked)} acknowledged, errors {load.errors}, gap {gap:.1f} s",
              flush=True)

    @check("T4b the primary cut off from every network (DNS and etcd gone): it stops taking writes within "
           "Patroni's ttl, one primary, no loss", "T4b")
    def _():
        with cluster.grpc() as c:
            c.create_session("t4b")
        old = cluster.leader()
        cut_from = [f"{PROJECT}_repl", f"{PROJECT}_data"]
        with Load(cluster, "t4b", descriptors) as load:
            time.sleep(4)
            cut = time.monotonic()
            for network in cut_from:
                sh("docker", "network", "disconnect", network, cluster.container(old))
            new = until("a new leader", lambda: cluster.leader_other_than(old), 90)
            elected = time.monotonic()
            until("the cut-off primary stops taking writes", lambda: cluster.not_writable(old), 90, every=0.5)
            writable_for = time.monotonic() - cut
            until("writes acknowledged again", lambda: load.ack_times and load.ack_times[-1] > cut + 0.5, 90)
            time.sleep(3)
            gap = load.gap(cut)
        load.verify(cluster, "T4b during the cut")
        both = max(0.0, cut + writable_for - elected)
        figures.append(("a primary cut off from every network: writable after the cut for, s", f"{writable_for:.1f}"))
        figures.append(("  ... while a new primary was elected (two writable), s", f"{both:.1f}"))
        figures.append(("  ... write gap, s", f"{gap:.1f}"))
        assert both <= 10, f"two writable primaries for {both:.1f} s (Patroni's ttl is 10 s)"
        assert gap < 30, f"writes stalled {gap:.1f} s"
        # Each network with the names compose gave it there: without its service name on the
        # data network the loopd nodes cannot resolve it, and once it is the primary again (T8's
        # restart may elect it) no node reaches the database (CI's failed run of 102610e).
        sh("docker", "network", "connect", "--alias", f"{old}-repl", cut_from[0], cluster.container(old))
        sh("docker", "network", "connect", "--alias", old, cut_from[1], cluster.container(old))
        resolved = sh("docker", "exec", cluster.container("loopd1"), "getent", "hosts", old, check=False)
        assert resolved, f"{old} is not resolvable from loopd1 after it rejoined the data network"
        until("the old primary back as a standby", cluster.healthy, 120, every=1)
        load.verify(cluster, "T4b after it rejoined")
        print(f"     {old} -> {new}; {len(load.acked)} acknowledged, errors {load.errors}, writable "
              f"{writable_for:.1f} s after the cut, gap {gap:.1f} s", flush=True)

    def t4c():
        with cluster.grpc() as c:
            c.create_session("t4c")
        old = cluster.leader()
        with Load(cluster, "t4c", descriptors) as load:
            time.sleep(4)
            frozen = time.monotonic()
            cluster.paused.add(old)
            sh("docker", "pause", cluster.container(old))
            try:
                new = until("a new leader", lambda: cluster.leader_other_than(old), 90)
                until("writes acknowledged again", lambda: load.ack_times and load.ack_times[-1] > frozen + 0.5, 90)
                time.sleep(max(0.0, 20 - (time.monotonic() - frozen)))
            finally:
                sh("docker", "unpause", cluster.container(old))
                cluster.paused.discard(old)
            thawed = time.monotonic()
            # A thawed primary that lost its leader key restarts as a standby.
            until("the thawed primary demoted", lambda: cluster.not_writable(old), 60, every=0.5)
            writable_after = time.monotonic() - thawed
            # The watcher may see two writable servers only in this window (the bound: ttl).
            watch.allowed.append((thawed - 1, thawed + writable_after + 2))
            time.sleep(3)
            gap = load.gap(frozen)
        load.verify(cluster, "T4c during the freeze and the thaw")
        figures.append(("a primary frozen 20 s: write gap, s", f"{gap:.1f}"))
        figures.append(("  ... thawed, writable until Patroni demoted it, s", f"{writable_after:.1f}"))
        assert gap < 30, f"writes stalled {gap:.1f} s"
        assert writable_after <= 10, f"the thawed old primary stayed writable {writable_after:.1f} s (ttl 10 s)"
        until("the old primary back as a standby", cluster.healthy, 120, every=1)
        load.verify(cluster, "T4c after it rejoined")
        print(f"     {old} -> {new}; {len(load.acked)} acknowledged, errors {load.errors}, gap {gap:.1f} s, "
              f"writable {writable_after:.1f} s after the thaw", flush=True)

    @check("T4c the primary frozen (docker pause) for 20 s: a new primary takes the writes; thawed, the old "
           "one is demoted within Patroni's ttl and no loopd node writes to it; no loss", "T4c")
    def _():
        try:
            t4c()
        except AssertionError:
            for n in NODES:  # what each node said meanwhile
                lines = [x for x in logs(cluster.container(n)).splitlines() if "WARN" in x or "ERROR" in x]
                print(f"---- {n} ----\n" + "\n".join(x[:400] for x in lines[-25:]), flush=True)
            raise

    @check("T7 both standbys killed: writes refused at once (UNAVAILABLE, not ready), none acknowledged; "
           "writes again once a standby streams", "T7")
    def _():
        with cluster.grpc() as c:
            c.create_session("t7")
            c.add_frame("t7", "w", Frame(descriptor=descriptors[0], frame_id=0))
        leader = until("a primary", cluster.leader, 60)
        standbys = [p for p in PG if p != leader]
        for pg in standbys:
            sh("docker", "kill", "-s", "KILL", cluster.container(pg))
        killed = time.monotonic()

        def not_ready(node):
            try:
                with urllib.request.urlopen(f"http://{cluster.addr(node, 8080)}/readyz", timeout=5):
                    return False
            except urllib.error.HTTPError as e:
                return e.code == 503
        until("every loopd node not ready", lambda: all(not_ready(n) for n in NODES), 30)
        figures.append(("every node not ready after both standbys were killed, s", f"{time.monotonic() - killed:.1f}"))
        refused = []
        with cluster.grpc("loopd1") as direct:
            for i in (1, 2):
                start = time.monotonic()
                try:
                    direct.add_frame("t7", "w", Frame(descriptor=descriptors[i], frame_id=i))
                    raise AssertionError("a write was acknowledged with no standby streaming")
                except grpc.RpcError as e:
                    assert e.code() == grpc.StatusCode.UNAVAILABLE and "standby" in e.details(), e
                    refused.append(time.monotonic() - start)
        assert max(refused) < 5, f"refusals took {refused} s"
        figures.append(("a write with no standby streaming refused in, s", f"{max(refused):.2f}"))
        for pg in standbys:
            cluster.compose("start", pg)
        until("a synchronous standby streaming again", cluster.healthy, 180, every=1)
        back = time.monotonic()

        def written():
            with cluster.grpc() as c:
                try:
                    c.add_frame("t7", "w", Frame(descriptor=descriptors[1], frame_id=1))
                except grpc.RpcError as e:
                    if e.code() != grpc.StatusCode.ALREADY_EXISTS:
                        raise
                return True
        until("a write acknowledged again", written, 60)
        figures.append(("writes again after a standby streamed again, s", f"{time.monotonic() - back:.1f}"))
        stored = sorted(cluster.stored("t7"))
        assert stored == [0, 1], f"t7 holds {stored}: frame 2 was refused, frame 1 stored once"

    @check("T8 every container restarted at once: the cluster comes back by itself, nothing acknowledged lost", "T8")
    def _():
        with cluster.grpc() as c:
            c.create_session("t8")
            for i in range(5):
                c.add_frame("t8", "w", Frame(descriptor=descriptors[i], frame_id=i))
        start = time.monotonic()
        cluster.compose("restart", "-t", "3")
        cluster.ips.clear()
        until("a primary with a synchronous standby", cluster.healthy, 180, every=1)
        # CI's run of 102610e gave up here: T4b had put its old primary back on the data network
        # without its name, so once T8's restart elected that server again no node could resolve
        # the primary (fixed in T4b, which now checks the name). wait_node says why it gives up.
        for n in NODES:
            cluster.wait_node(n, 240)
        cluster.ips.clear()

        def written():
            with cluster.grpc() as c:
                c.add_frame("t8", "w", Frame(descriptor=descriptors[5], frame_id=5))
                return True
        until("a write acknowledged through the balancer", written, 60)
        figures.append(("whole-cluster restart until writes are acknowledged, s", f"{time.monotonic() - start:.1f}"))
        assert sorted(cluster.stored("t8")) == list(range(6))
        for n in NODES:
            restarts = sh("docker", "inspect", "-f", "{{.RestartCount}} {{.State.Status}}", cluster.container(n))
            assert restarts.endswith("running"), f"{n}: {restarts}"

    @check("never two writable primaries, sampled every second through every fault", "primary")
    def _():
        watch.stop()
        assert watch.samples > 30, watch.samples
        # Two writable servers only right after T4c's thaw (bounded there by Patroni's ttl): a
        # thawed old primary is writable until Patroni demotes it (loopd's nodes refuse it: an
        # older timeline). Anywhere else, never.
        outside = [d for d in watch.double if not any(a <= d[0] <= b for a, b in watch.allowed)]
        assert not outside, f"two writable primaries at once: {outside[:5]}"
        figures.append(("samples of the writable primaries (never more than one outside a thaw)", str(watch.samples)))

    @check("the example robot streams the corridor through the balancer, unchanged", "robot")
    def _():
        name = f"{PROJECT}-robot"
        cluster.compose("--profile", "robots", "run", "-d", "--name", name, "-e", f"LOOPD_KEY={cluster.key}", "robot",
                        "--session", "robot", "--create", "--robot", "mapper", "--frame-id-base", "0", "--no-verify",
                        "/shared/corridor/ref", "--summary", "/out/robot.json")
        code = sh("timeout", "600", "docker", "wait", name)
        out = logs(name)[-1500:]
        sh("docker", "rm", name, check=False)
        assert code == "0", f"robot exited {code}: {out}"
        summary = json.loads((pathlib.Path(cluster.env["LOOPD_TEST_OUT"]) / "robot.json").read_text())
        refs = len(list((DATA / "corridor/ref").glob("*.jpg")))
        assert summary["acked"] == list(range(refs)) and summary["failed"] == 0, summary
        assert sorted(cluster.stored("robot")) == list(range(refs))


def query_request(session: str, d: list[float]):
    r = pb.QueryRequest(session_id=session, robot_id="q")
    r.descriptor.values.extend(d)
    return r


class PrimaryWatch:
    """Samples which PostgreSQL servers are writable, every second, in the background."""

    def __init__(self, cluster: Cluster):
        self.cluster, self.samples, self.double = cluster, 0, []
        # (start, end) windows where two writable servers are expected (a thawed primary).
        self.allowed: list[tuple[float, float]] = []
        self.done = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def start(self) -> None:
        self.thread.start()

    def run(self) -> None:
        while not self.done.wait(1.0):
            asked = time.monotonic()
            w = self.cluster.writable()
            self.samples += 1
            if len(w) > 1:
                self.double.append((asked, w))

    def stop(self) -> None:
        self.done.set()
        self.thread.join()


if __name__ == "__main__":
    main()
