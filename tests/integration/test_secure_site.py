"""Secure site: the dev PKI of ``sogm-service certs`` and the Zenoh configs it writes, proven with
real Zenoh sessions on 127.0.0.1 over mutual TLS with access control by certificate name.

Two topologies, each with one PKI for the module: ``direct`` (the server is a peer listening on
the TLS endpoint and carries the access control) and ``router`` (a router in the middle carries
it; the server, robots and viewers are its clients).  The server is a plain session standing in
for ``serve``: a queryable on ``sogm/default/submap`` and ``sogm/default/tiles/**``, a liveliness
token ``sogm/default/@server/<name>`` and one subscriber on ``**`` (a superset of what ``serve``
listens to), whose one handler keeps arrival order.

"Never arrives" is proven without sleeping: the forbidden message is sent first, then a permitted
marker on the same link; once the marker has arrived, the forbidden message would have arrived
before it (one link, one priority, one handler, in order).
"""

from __future__ import annotations

import copy
import datetime as dt
import itertools
import json
import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from cryptography.hazmat.primitives import serialization

from sogm_service.apps import certs
from sogm_service.apps.certs import Pki, init_pki, load_ca, make_ca, make_identity
from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import free_tcp_endpoint, wait_listening
from sogm_service.wire import codec
from sogm_service.wire.messages import PoseMessage
from sogm_service.wire.queries import GridReply
from tests.unit.apps.test_certs import config_dict

pytestmark = pytest.mark.integration

GET_TIMEOUT = 2.0
WAIT = 10.0
REPO = Path(__file__).resolve().parents[2]
_unique = itertools.count()


def tls_endpoint() -> str:
    return free_tcp_endpoint().replace("tcp/", "tls/", 1)


def open_file(path: Path) -> zenoh.Session:
    return zenoh.open(zenoh.Config.from_file(str(path)))


def open_dict(cfg: dict[str, Any]) -> zenoh.Session:
    return zenoh.open(zenoh.Config.from_json5(json.dumps(cfg)))


def with_identity(base: dict[str, Any], cert: Path | None, key: Path | None) -> dict[str, Any]:
    """``base`` with another client certificate and key (or none at all)."""
    cfg = copy.deepcopy(base)
    tls = cfg["transport"]["link"]["tls"]
    for field_, value in (("connect_certificate", cert), ("connect_private_key", key)):
        if value is None:
            tls.pop(field_, None)
        else:
            tls[field_] = str(value)
    return cfg


def payloads(session: zenoh.Session, key: str) -> list[bytes]:
    """The payloads of the OK replies to one get (errors become ``b'ERR:...'``)."""
    out = []
    for reply in session.get(key, timeout=GET_TIMEOUT):
        if reply.ok is not None:
            out.append(reply.ok.payload.to_bytes())
        else:
            assert reply.err is not None
            out.append(b"ERR:" + reply.err.payload.to_bytes())
    return out


def token_keys(session: zenoh.Session, key: str) -> list[str]:
    return sorted(str(r.ok.key_expr) for r in session.liveliness().get(key, timeout=GET_TIMEOUT)
                  if r.ok is not None)


class Recorder:
    """A subscriber callback that records (key, payload) in arrival order."""

    def __init__(self) -> None:
        self._cv = threading.Condition()
        self.items: list[tuple[str, bytes]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cv:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))
            self._cv.notify_all()

    def wait_for(self, key: str, payload: bytes, timeout: float = WAIT) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: (key, payload) in self.items, timeout)

    def payloads_of(self, key: str) -> list[bytes]:
        with self._cv:
            return [p for k, p in self.items if k == key]

    def with_payload(self, payload: bytes) -> list[str]:
        with self._cv:
            return [k for k, p in self.items if p == payload]


def tag(label: str) -> bytes:
    return f"{label}-{next(_unique)}".encode()


@dataclass
class Site:
    """One secure site on 127.0.0.1: its PKI, the node carrying the ACL, the stand-in server."""

    topology: str
    pki: Pki
    server: zenoh.Session
    heard: Recorder  # everything that reaches the stand-in server
    sessions: list[zenoh.Session] = field(default_factory=list)
    declared: list[Any] = field(default_factory=list)

    def open(self, name: str) -> zenoh.Session:
        return open_file(self.pki.config(name))


@pytest.fixture(scope="module", params=["direct", "router"])
def site(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory,
         ) -> Iterator[Site]:
    topology = request.param
    pki = init_pki(tmp_path_factory.mktemp(f"pki-{topology}"),
                   server_names=["srv", "srv2"], robot_names=["robotA", "robotB"],
                   viewer_names=["view"], router_name="rt" if topology == "router" else None,
                   endpoint=tls_endpoint())
    sessions: list[zenoh.Session] = []
    try:
        if topology == "router":
            sessions.append(open_file(pki.config("rt")))
        server = open_file(pki.config("srv"))
        sessions.append(server)
        heard = Recorder()
        s = Site(topology, pki, server, heard, sessions)
        s.declared += [
            server.declare_subscriber("**", heard),
            # What serve declares: robots' publishers send only when they know of these.
            server.declare_subscriber("ism/**", lambda s: None),
            server.declare_subscriber("pose/**", lambda s: None),
            server.declare_queryable("sogm/default/submap",
                                     lambda q: q.reply(q.key_expr, b"server")),
            server.declare_queryable("sogm/default/tiles/**",
                                     lambda q: q.reply(q.key_expr, b"tile")),
            server.liveliness().declare_token("sogm/default/@server/srv"),
        ]
        # Ready when a robot sees the server's queryable and the subscriber hears its puts.
        with s.open("robotA") as probe:
            assert _eventually(lambda: payloads(probe, "sogm/default/submap") == [b"server"])
            mark = tag("ready")
            probe.put("ism/robotA/ready", mark)
            assert heard.wait_for("ism/robotA/ready", mark)
        yield s
    finally:
        for z in reversed(sessions):
            z.close()


def _eventually(pred: Any, tries: int = 50) -> bool:
    ev = threading.Event()
    for _ in range(tries):
        if pred():
            return True
        ev.wait(0.1)
    return bool(pred())


# --------------------------------------------------------------------------- the PKI files


# --------------------------------------------------------------------------- who may connect

def test_client_without_certificate_cannot_connect(site: Site) -> None:
    base = config_dict(site.pki.config("robotA"))
    # A client gives up at once: zenoh.open raises.
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        open_dict(with_identity(base, None, None))
    # A plain TCP client on the TLS port: the same.
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        open_dict({"mode": "client", "connect": {"endpoints": [
            site.pki.endpoint.replace("tls/", "tcp/", 1)]},
            "scouting": {"multicast": {"enabled": False}}})
    # A peer opens anyway (it keeps retrying in the background) but reaches no one.
    peer_cfg = with_identity(base, None, None)
    peer_cfg["mode"] = "peer"
    mark = tag("nocert")
    with open_dict(peer_cfg) as peer:
        assert peer.info.peers_zid() == [] and peer.info.routers_zid() == []
        peer.put("ism/robotA/nocert", mark)
        assert payloads(peer, "sogm/default/submap") == []
    assert site.heard.with_payload(mark) == []


def test_certificate_from_another_ca_cannot_connect(site: Site, tmp_path: Path) -> None:
    other = make_ca("impostor CA")
    # The impostor even claims the server's name.
    cert, key = make_identity(other, "srv")
    certs.write_cert(tmp_path / "o.crt", cert)
    certs.write_key(tmp_path / "o.key", key)
    base = config_dict(site.pki.config("robotA"))
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        open_dict(with_identity(base, tmp_path / "o.crt", tmp_path / "o.key"))


@pytest.mark.parametrize("window", ["expired", "not_yet_valid"])
def test_certificate_outside_its_validity_is_refused(site: Site, tmp_path: Path,
                                                     window: str) -> None:
    now = dt.datetime.now(dt.UTC)
    start, end = ((now - dt.timedelta(days=10), now - dt.timedelta(days=1))
                  if window == "expired" else
                  (now + dt.timedelta(days=1), now + dt.timedelta(days=10)))
    cert, key = make_identity(load_ca(site.pki.directory), "robotA", not_before=start,
                              not_after=end)
    certs.write_cert(tmp_path / "e.crt", cert)
    certs.write_key(tmp_path / "e.key", key)
    base = config_dict(site.pki.config("robotA"))
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        open_dict(with_identity(base, tmp_path / "e.crt", tmp_path / "e.key"))
    # The same robot with its valid certificate connects (the refusal is the validity's).
    with open_dict(base) as ok:
        assert payloads(ok, "sogm/default/submap") == [b"server"]


def test_unknown_name_from_the_site_ca_connects_but_may_do_nothing(site: Site,
                                                                   tmp_path: Path) -> None:
    cert, key = make_identity(load_ca(site.pki.directory), "intruder")
    certs.write_cert(tmp_path / "i.crt", cert)
    certs.write_key(tmp_path / "i.key", key)
    base = config_dict(site.pki.config("robotA"))
    mark = tag("intruder")
    with open_dict(with_identity(base, tmp_path / "i.crt", tmp_path / "i.key")) as intruder:
        intruder.put("ism/intruder/x", mark)
        intruder.put("ism/robotA/x", mark)
        assert payloads(intruder, "sogm/default/submap") == []
        assert token_keys(intruder, "sogm/default/@server/*") == []
        with site.open("robotA") as robot:  # the server is there for a known robot
            assert payloads(robot, "sogm/default/submap") == [b"server"]
            fence = tag("fence")
            robot.put("ism/robotA/fence", fence)
            assert site.heard.wait_for("ism/robotA/fence", fence)
    assert site.heard.with_payload(mark) == []


# --------------------------------------------------------------------------- what robots may do

def test_robot_puts_only_under_its_own_name(site: Site) -> None:
    forged, own = tag("forged"), tag("own")
    with site.open("robotA") as robot:
        # Declared publishers with BLOCK, as MapClient.publish_ism and publish_pose use.
        pubs = {k: robot.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                for k in ("ism/robotB/laser/obstacle", "ism/robotA/laser/obstacle",
                          "pose/robotB", "pose/robotA")}
        pubs["ism/robotB/laser/obstacle"].put(forged)
        pubs["pose/robotB"].put(forged)
        robot.put("pose/robotA/extra", forged)
        robot.delete("ism/robotA/laser/obstacle")
        robot.put("sogm/default/events/tile", forged)  # forging a tile event
        pubs["ism/robotA/laser/obstacle"].put(own)
        pubs["pose/robotA"].put(own)
        assert site.heard.wait_for("ism/robotA/laser/obstacle", own)
        assert site.heard.wait_for("pose/robotA", own)
        for p in pubs.values():
            p.undeclare()
    assert site.heard.with_payload(forged) == []
    assert site.heard.payloads_of("ism/robotA/laser/obstacle") == [own]  # no delete arrived


def test_impostor_queryable_and_token_answer_no_one(site: Site) -> None:
    with site.open("robotB") as impostor, site.open("robotA") as robot, \
            site.open("view") as viewer:
        q = impostor.declare_queryable("sogm/default/submap",
                                       lambda q: q.reply(q.key_expr, b"impostor"))
        q2 = impostor.declare_queryable("sogm/default/**",
                                        lambda q: q.reply(q.key_expr, b"impostor"))
        token = impostor.liveliness().declare_token("sogm/default/@server/fake")
        # Once the node answers the impostor's liveliness query, it has handled the
        # declarations sent before it on the same link.
        assert "sogm/default/@server/srv" in token_keys(impostor, "sogm/default/@server/*")
        answers = [payloads(robot, "sogm/default/submap") for _ in range(20)]
        assert answers == [[b"server"]] * 20
        assert payloads(viewer, "sogm/default/submap") == [b"server"]
        assert token_keys(robot, "sogm/default/@server/*") == ["sogm/default/@server/srv"]
        assert token_keys(viewer, "sogm/default/@server/*") == ["sogm/default/@server/srv"]
        token.undeclare()
        q2.undeclare()
        q.undeclare()


def test_robot_reads_events_and_own_rejections_only(site: Site) -> None:
    heard = Recorder()  # on ``**``: everything that reaches the robot, in arrival order
    with site.open("robotA") as robot:
        subs = [robot.declare_subscriber("**", heard)] + [
            robot.declare_subscriber(k, lambda s: None) for k in (
                "sogm/default/events/**", "sogm/default/rejections/robotA",
                # Denied declarations: the node never routes these to the robot.
                "sogm/default/rejections/robotB", "sogm/default/tiles/**", "ism/**",
                "pose/**")]
        secret, event = tag("secret"), tag("event")
        # The subscriptions are declared once the server hears the robot's marker.
        fence = tag("fence")
        robot.put("pose/robotA", fence)
        assert site.heard.wait_for("pose/robotA", fence)
        with site.open("robotB") as other:
            other.put("ism/robotB/x", secret)
            other.put("pose/robotB", secret)
            fence = tag("fence")
            other.put("pose/robotB", fence)
            assert site.heard.wait_for("pose/robotB", fence)
        site.server.put("sogm/default/tiles/0/0", secret)
        site.server.put("sogm/default/rejections/robotB", secret)
        site.server.put("sogm/default/matching/robotB", secret)
        site.server.put("sogm/default/rejections/robotA", event)
        site.server.put("sogm/default/events/tile", event)
        assert heard.wait_for("sogm/default/events/tile", event)
        assert heard.with_payload(event) == ["sogm/default/rejections/robotA",
                                             "sogm/default/events/tile"]
        assert heard.with_payload(secret) == []
        for s in subs:
            s.undeclare()


def test_robot_and_viewer_cannot_read_tiles_but_a_server_can(site: Site) -> None:
    with site.open("robotA") as robot, site.open("view") as viewer, \
            site.open("srv2") as server2:
        for who in (robot, viewer):
            assert payloads(who, "sogm/default/tiles/**") == []
            assert payloads(who, "sogm/default/tiles/0/0") == []
            assert payloads(who, "sogm/**") == []
            assert payloads(who, "sogm/default/submap") == [b"server"]
        assert _eventually(lambda: payloads(server2, "sogm/default/tiles/0/0") == [b"tile"])


def test_viewer_cannot_put_and_sees_poses(site: Site) -> None:
    forged = tag("viewer")
    seen = Recorder()
    with site.open("view") as viewer, site.open("robotA") as robot:
        sub = viewer.declare_subscriber("pose/**", seen)
        for key in ("ism/view/x", "ism/robotA/x", "pose/view", "pose/robotA",
                    "sogm/default/events/tile"):
            viewer.put(key, forged)
        viewer.delete("pose/robotA")
        # The viewer's query is answered after its puts went through the node (one link, in
        # order); the robot's marker goes after that on the server's one handler.
        assert payloads(viewer, "sogm/default/submap") == [b"server"]
        pose = tag("pose")
        robot.put("pose/robotA", pose)
        assert site.heard.wait_for("pose/robotA", pose)
        assert _eventually(lambda: seen.payloads_of("pose/robotA")[-1:] == [pose])
        sub.undeclare()
    assert site.heard.with_payload(forged) == []
    assert site.heard.payloads_of("pose/robotA").count(pose) == 1


def _stand_in(path: Path) -> tuple[zenoh.Session, Recorder]:
    server = open_file(path)
    heard = Recorder()
    server.declare_subscriber("**", heard)
    server.declare_subscriber("ism/**", lambda s: None)
    server.declare_queryable("sogm/default/submap", lambda q: q.reply(q.key_expr, b"server"))
    return server, heard


def test_added_robot_and_removed_robot_after_a_restart(tmp_path: Path) -> None:
    pki = init_pki(tmp_path, server_names=["srv"], robot_names=["robotA"],
                   endpoint=tls_endpoint())
    (tmp_path / "keep").mkdir()
    for ext in ("crt", "key"):  # robotA keeps its files when the site drops it
        (tmp_path / "keep" / f"robotA.{ext}").write_bytes(
            (tmp_path / f"robotA.{ext}").read_bytes())
    old_a = with_identity(config_dict(pki.config("robotA")), tmp_path / "keep" / "robotA.crt",
                          tmp_path / "keep" / "robotA.key")
    certs.add_identity(tmp_path, "robotC")
    certs.remove_identity(tmp_path, "robotA")
    server, heard = _stand_in(pki.config("srv"))  # (re)started with the new rules
    try:
        own, forged = tag("own"), tag("forged")
        with open_dict(old_a) as dropped:  # still a valid certificate of the site CA ...
            dropped.put("ism/robotA/x", forged)  # ... but no rule for its name any more
            assert payloads(dropped, "sogm/default/submap") == []
        with open_file(pki.config("robotC")) as robot:
            robot.put("ism/robotA/x", forged)
            robot.put("ism/robotC/x", own)
            assert heard.wait_for("ism/robotC/x", own)
            assert payloads(robot, "sogm/default/submap") == [b"server"]
        assert heard.with_payload(forged) == []
    finally:
        server.close()


def test_a_ca_bundle_admits_both_cas_for_a_rollover(tmp_path: Path) -> None:
    """CA rotation relies on a root_ca_certificate file holding the old and the new CA."""
    pki = init_pki(tmp_path, server_names=["srv"], robot_names=["robotA"],
                   endpoint=tls_endpoint())
    new = make_ca("next site CA")
    bundle = tmp_path / "bundle.crt"
    bundle.write_bytes(pki.ca_cert.read_bytes()
                       + new.cert.public_bytes(serialization.Encoding.PEM))
    cert, key = make_identity(new, "robotA")
    certs.write_cert(tmp_path / "new.crt", cert)
    certs.write_key(tmp_path / "new.key", key)
    srv_cfg = config_dict(pki.config("srv"))
    srv_cfg["transport"]["link"]["tls"]["root_ca_certificate"] = str(bundle)
    robot_new = with_identity(config_dict(pki.config("robotA")), tmp_path / "new.crt",
                              tmp_path / "new.key")
    robot_new["transport"]["link"]["tls"]["root_ca_certificate"] = str(bundle)
    server = open_file(pki.config("srv"))  # trusting the old CA alone: refused
    try:
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            open_dict(robot_new)
    finally:
        server.close()
    server = open_dict(srv_cfg)
    try:
        server.declare_queryable("sogm/default/submap",
                                 lambda q: q.reply(q.key_expr, b"server"))
        for cfg in (config_dict(pki.config("robotA")), robot_new):  # old and new certificate
            with open_dict(cfg) as robot:
                assert payloads(robot, "sogm/default/submap") == [b"server"]
    finally:
        server.close()


# --------------------------------------------------------------------------- deploy/secure

TEMPLATE_DIR = REPO / "deploy" / "secure"


def render_template(name: str, values: dict[str, str]) -> str:
    text = (TEMPLATE_DIR / name).read_text()
    for k, v in values.items():
        text = text.replace("${" + k + "}", v)
    left = re.findall(r"\$\{[A-Z_]+\}", text)
    assert not left, f"{name}: unfilled placeholders {left}"
    return text


def normalized(config_text: str) -> dict[str, Any]:
    """The config as zenoh reads it (defaults filled in, comments gone)."""
    d: dict[str, Any] = json.loads(str(zenoh.Config.from_json5(config_text)))
    return d


def test_templates_match_the_generator_and_work(tmp_path: Path) -> None:
    """deploy/secure/*.json5, filled in, equal what `certs init --router` writes for the same
    names (same access control) and hold a robot to its own keys through a router."""
    endpoint = tls_endpoint()
    pki = init_pki(tmp_path, server_names=["server1"], robot_names=["robot1", "robot2"],
                   viewer_names=["viewer1"], router_name="router1", endpoint=endpoint)

    def values(name: str) -> dict[str, str]:
        return {"CA_CERT": str(pki.ca_cert), "CERT": str(pki.cert(name)),
                "KEY": str(pki.key(name)), "ENDPOINT": endpoint, "LISTEN": endpoint}

    texts = {role: render_template(f"{role}.json5", values(name)) for role, name in (
        ("router", "router1"), ("server", "server1"), ("robot", "robot1"),
        ("viewer", "viewer1"))}
    def acl(text: str) -> dict[str, Any]:  # the order of the lists means nothing to zenoh
        a = normalized(text)["access_control"]
        for part in ("rules", "subjects", "policies"):
            a[part] = {x["id"]: x for x in a[part]}
        return a

    assert acl(texts["router"]) == acl(json.dumps(certs.zenoh_config(pki, "router1")))
    for role, name in (("router", "router1"), ("server", "server1"), ("robot", "robot1"),
                       ("viewer", "viewer1")):
        got, want = normalized(texts[role]), normalized(
            json.dumps(certs.zenoh_config(pki, name)))
        for part in ("mode", "listen", "connect", "scouting", "transport"):
            assert got[part] == want[part], (role, part)

    heard = Recorder()
    with zenoh.open(zenoh.Config.from_json5(texts["router"])), \
            zenoh.open(zenoh.Config.from_json5(texts["server"])) as server:
        sub = server.declare_subscriber("**", heard)
        q = server.declare_queryable("sogm/default/submap",
                                     lambda q: q.reply(q.key_expr, b"server"))
        with zenoh.open(zenoh.Config.from_json5(texts["robot"])) as robot:
            assert _eventually(lambda: payloads(robot, "sogm/default/submap") == [b"server"])
            forged, own = tag("forged"), tag("own")
            robot.put("ism/robot2/x", forged)
            robot.put("ism/robot1/x", own)
            assert heard.wait_for("ism/robot1/x", own)
        assert heard.with_payload(forged) == []
        q.undeclare()
        sub.undeclare()


# --------------------------------------------------------------------------- the real server

@dataclass
class RealSite:
    pki: Pki
    proc: subprocess.Popen[bytes]
    log: Path


@pytest.fixture(scope="module")
def real_site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RealSite]:
    """``sogm-service serve`` as a child process, its Zenoh session from the server identity's
    generated config (``[zenoh] config_file``; it listens and enforces the access control)."""
    d = tmp_path_factory.mktemp("real")
    pki = init_pki(d / "pki", server_names=["srv"], robot_names=["robotA", "robotB"],
                   viewer_names=["view"], endpoint=tls_endpoint())
    toml = d / "serve.toml"
    toml.write_text(f'[zenoh]\nconfig_file = "{pki.config("srv")}"\n', encoding="utf-8")
    log = d / "serve.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "sogm_service", "serve", "--config", str(toml)],
            stdout=out, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        wait_listening(pki.endpoint.replace("tls/", "tcp/", 1), 60, lambda: proc.poll() is not None,
                       lambda: log.read_text(errors="replace"))
        with MapClient(open_file(pki.config("robotA")), timeout=1.0, owns_session=True) as c:
            up = _eventually(lambda: proc.poll() is None and len(c.servers()) == 1, tries=300)
        assert up, log.read_text(errors="replace")
        yield RealSite(pki, proc, log)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)


def client_as(site: RealSite, name: str) -> MapClient:
    return MapClient(open_file(site.pki.config(name)), timeout=GET_TIMEOUT, owns_session=True)


def test_real_server_fuses_only_a_robots_own_isms(real_site: RealSite) -> None:
    grid = np.full((32, 32), 230, np.uint8)
    window = {"x": 0.8, "y": 0.8, "width": 1.6, "height": 1.6,
              "layers": "robotA/laser/obstacle"}

    def fused(c: MapClient) -> int:
        return c.stats().counters.get("isms_fused", 0)

    with client_as(real_site, "robotA") as robot, client_as(real_site, "view") as viewer:
        robot.publish_ism("ism/robotA/laser/obstacle", grid, resolution=0.05)
        assert _eventually(lambda: fused(robot) == 1, tries=100)
        before = codec.decode(GridReply, robot.get_raw(robot.key("submap"), window))
        # Forged ISMs over the same tiles: robotA as robotB, the viewer as anyone.
        robot.publish_ism("ism/robotB/laser/obstacle", grid, resolution=0.05, robot="robotB")
        viewer.publish_ism("ism/robotA/laser/obstacle", grid, resolution=0.05)
        viewer.publish_ism("ism/view/laser/obstacle", grid, resolution=0.05)
        # A fence on the same tiles, in another layer: per-tile order is arrival order, so a
        # forged ISM that had arrived would be fused before it.
        robot.publish_ism("ism/robotA/laser/fence", grid, resolution=0.05)
        assert _eventually(lambda: fused(robot) >= 2, tries=100)
        counters = robot.stats().counters
        assert counters.get("isms_fused", 0) == 2
        assert counters.get("isms_rejected", 0) == 0
        assert sorted(viewer.info().layers) == ["robotA/laser/fence", "robotA/laser/obstacle"]
        after = codec.decode(GridReply, robot.get_raw(robot.key("submap"), window))
        assert after.layers == before.layers == ["robotA/laser/obstacle"]
        assert after.data == before.data  # the layer is bit-identical (only the stamp moved)
        assert robot.tiles() == {}  # tiles/** is for servers only
        assert viewer.tiles(0, 0) == {}


def test_real_server_impostor_answers_no_query(real_site: RealSite) -> None:
    with client_as(real_site, "robotB") as impostor, client_as(real_site, "robotA") as robot:
        q = impostor.session.declare_queryable(
            "sogm/default/submap", lambda q: q.reply(q.key_expr, b"not msgpack"))
        token = impostor.session.liveliness().declare_token("sogm/default/@server/fake")
        assert impostor.servers() != []  # a round trip: the node has seen the declarations
        answers = [payloads(robot.session, "sogm/default/submap?width=1;height=1")
                   for _ in range(20)]
        assert [len(a) for a in answers] == [1] * 20  # one answer each: the server's
        assert all(a[0] != b"not msgpack" and not a[0].startswith(b"ERR:") for a in answers)
        assert robot.submap(width=1.0, height=1.0).layers is not None  # decodes
        assert len(robot.servers()) == 1 and "fake" not in robot.servers()
        token.undeclare()
        q.undeclare()


def test_real_server_a_robot_cannot_move_another_robot(real_site: RealSite) -> None:
    forged = PoseMessage(robot="robotB", frame="map", stamp=1.0, x=50.0, y=50.0, yaw=0.0)
    with client_as(real_site, "robotA") as robot:
        robot.publish_raw("pose/robotA", codec.encode(forged))  # its own key, another's name
        robot.publish_pose("robotA", 1.0, 1.0, stamp=2.0)  # the fence: same key, later
        assert _eventually(lambda: "robotA" in {e.robot for e in robot.robots().robots},
                           tries=100)
        assert "robotB" not in {e.robot for e in robot.robots().robots}
