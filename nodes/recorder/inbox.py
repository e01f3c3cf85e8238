"""What the recorder subscribes to while it records (``Inbox``), learnt from the ROS 2 graph."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from typing import Any

import zenoh

from exolink import messaging, roles

# Topics subscribed one by one, learnt from graph tokens, which any login may declare (roles:
from exolink.wire import rosgraph

# "ros graph"); each costs a subscription (its inbox, the router's work). The appliance's own
# sessions have a budget of their own, so tokens from elsewhere never crowd out what the
# appliance publishes; other sessions (by the zid their tokens name) are bounded each and
# together. What does not fit is refused and counted (``record status``, each file's stats).
MAX_TOPICS_PER_APPLIANCE_SESSION = 128  # an appliance node publishes < 20
MAX_TOPICS_PER_FOREIGN_SESSION = 64  # a laptop: `exolink play`, a ROS 2 node or bag
MAX_FOREIGN_TOPICS = 128
SESSIONS_QUERY_S = 0.5  # asking which sessions are the appliance's
# A node that (re)started is asked again this long after its token came: it declares its
# management queryables (what proves its session) just after the token.
SESSIONS_RETRY_S = 1.0
SESSIONS_GAP_S = 0.5  # never asked more often (alive tokens may come in bursts)
MAX_REFUSED_SESSIONS = 16  # sessions named in the refusal counts; the rest summed as "other"
TOKEN_RING = 4096  # graph and bundle tokens waiting for the loop


class Inbox:
    """What the recorder subscribes to, learnt from the ROS 2 graph as ``ros2 bag record`` does:
    each publisher's graph token names a topic, and a kept topic gets a subscription of its own,
    or is taken from its bundles when its publisher bundles it (messaging.bundle_key). One
    wildcard over the data keys would match a bundled topic's own key too, and every message of
    it would come through the router a second time. Samples wait in Zenoh ring channels.
    The recorder's own topics (its diagnostics, the log of the commands it is given: ``record
    start`` is one) come through a wildcard limited to its own session, at once: discovery
    takes a loop. Publishers outside the graph (no token) are not recorded, and a publisher's
    messages before the recorder saw its token are not either (as with ``ros2 bag record``):
    appliance nodes declare theirs at start (the command log's included). A topic some
    publisher bundles is taken from bundles only, while that publisher lives: a second,
    unbundled publisher of the same topic meanwhile is not recorded.

    Any login may declare graph tokens, so the appliance's own sessions are told apart by what
    only they can do: answer the appliance's management queries (on a board with logins, only
    the appliance's login may declare a queryable: exolink.roles). Their zids come from those
    answers (asked when recording starts and whenever a node's ``alive`` token comes, which
    again only the appliance may declare), and each gets a graph subscription of its own
    (``@ros2_lv/<domain>/<zid>/**``, history included): however many tokens others declare,
    the appliance's reach the recorder and fill a budget no other session shares. Other
    sessions' topics are bounded per session and together; what is refused is counted. Left
    open: the zid in a token is only text, so tokens forged with an appliance session's zid
    count against that session's budget (it takes 128 of them to crowd it out).
    """

    def __init__(
        self,
        session: Any,
        device: str,
        domain_id: int,
        selectors: list[str],
        kept: Any,
        ring: int,
    ) -> None:
        self.session, self.device, self.ring, self.kept = session, device, ring, kept
        self.selectors = [zenoh.KeyExpr(s) for s in selectors]
        self.bundled: set[str] = set()  # data keys taken from bundles
        self.subs: dict[str, Any] = {}  # data key -> its own subscription (other processes')
        self.published: set[str] = set()  # kept data keys the graph showed a publisher of
        self.zid = str(session.zid())
        self.domain_id = domain_id
        self.appliance: set[str] = {self.zid}  # zids of the appliance's own sessions
        self.owner: dict[str, str] = {}  # data key taken -> the zid whose token brought it
        self.per_session: dict[str, int] = {}  # zid -> topics taken for it
        self.foreign = 0  # topics taken for sessions not the appliance's
        self.refused = 0  # tokens over a budget
        self.refused_from: dict[str, int] = {}
        # When to ask which sessions are the appliance's (monotonic), and once more after that.
        self._ask_at, self._ask_again, self._asked = 0.0, math.inf, -math.inf
        self._own_graphs: dict[str, Any] = {}  # appliance zid -> its graph tokens
        own = [
            session.declare_subscriber(
                sel, zenoh.handlers.RingChannel(ring), allowed_origin=zenoh.Locality.SESSION_LOCAL
            )
            for sel in selectors
        ]
        bundles = messaging.bundle_selector(device)
        self.bundles = session.declare_subscriber(bundles, zenoh.handlers.RingChannel(ring))
        self.own = own
        lv = session.liveliness()
        self._bundle_tokens = lv.declare_subscriber(
            bundles, zenoh.handlers.RingChannel(TOKEN_RING), history=True
        )
        self._graph = lv.declare_subscriber(
            f"{rosgraph.ADMIN_SPACE}/{domain_id}/**",
            zenoh.handlers.RingChannel(TOKEN_RING),
            history=True,
        )
        self._nodes = lv.declare_subscriber(
            messaging.mgmt_key(device, "nodes", "*", "alive"), zenoh.handlers.RingChannel(256)
        )

    def discover(self) -> None:
        """Which sessions are the appliance's, when due; new bundle tokens (their topics come
        in bundles from now on: a subscription of the topic's own key is dropped), then new
        publishers in the graph: the appliance's sessions' first."""
        self._sessions()
        while (t := self._bundle_tokens.try_recv()) is not None:
            try:
                key = messaging.bundled_data_key(self.device, str(t.key_expr))
            except ValueError:
                continue
            if t.kind != zenoh.SampleKind.PUT:  # its publisher is gone: maybe back unbundled
                self.bundled.discard(key)
                if key in self.published:
                    self._subscribe(key)
                continue
            self.bundled.add(key)
            sub = self.subs.pop(key, None)
            if sub is not None:
                sub.undeclare()
        for graph in (*self._own_graphs.values(), self._graph):
            while (t := graph.try_recv()) is not None:
                if t.kind == zenoh.SampleKind.PUT:
                    self._token(str(t.key_expr))

    def _token(self, token: str) -> None:
        """A publisher's graph token: its topic taken if it is wanted and fits its budget."""
        try:
            entity = rosgraph.parse_token(token)
            if entity.kind != rosgraph.PUBLISHER or entity.zid == self.zid:
                return
            key = messaging.data_key_of(entity)
            if key in self.published or self.kept(key) is None or not self.wanted(key):
                return
        except Exception:  # anyone may declare a token: a bad one is not a topic
            return
        zid = entity.zid
        taken = self.per_session.get(zid, 0)
        if zid in self.appliance:
            full = taken >= MAX_TOPICS_PER_APPLIANCE_SESSION
        else:
            full = taken >= MAX_TOPICS_PER_FOREIGN_SESSION or self.foreign >= MAX_FOREIGN_TOPICS
        if full:
            self.refused += 1
            named = zid in self.refused_from or len(self.refused_from) < MAX_REFUSED_SESSIONS
            name = zid if named else "other"
            self.refused_from[name] = self.refused_from.get(name, 0) + 1
            return
        self.per_session[zid] = taken + 1
        self.foreign += zid not in self.appliance
        self.owner[key] = zid
        self.published.add(key)
        if key not in self.bundled:
            self._subscribe(key)

    def _sessions(self) -> None:
        """Asks which sessions are the appliance's when due: at the start, and when a node's
        ``alive`` token comes (now, and once more when its queryables are surely up)."""
        now = time.monotonic()
        while (t := self._nodes.try_recv()) is not None:
            if t.kind == zenoh.SampleKind.PUT:
                self._ask_at, self._ask_again = min(self._ask_at, now), now + SESSIONS_RETRY_S
        if now < self._ask_at or now - self._asked < SESSIONS_GAP_S:
            return
        self._asked, self._ask_at, self._ask_again = now, self._ask_again, math.inf
        key = messaging.mgmt_key(self.device, "nodes", "**", roles.APPLIANCE_USER)
        try:
            replies = self.session.get(
                key,
                payload=b"{}",
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=SESSIONS_QUERY_S,
            )
            zids = {str(r.replier_id.zid) for r in replies if r.replier_id is not None}
        except Exception:  # asked again when the next node starts
            return
        self._adopt(zids | {self.zid})

    def _adopt(self, zids: set[str]) -> None:
        """``zids`` answered as the appliance's: each gets a graph subscription of its own (its
        tokens so far come with it), one that no longer answers loses its (a node restarted:
        its old session is gone); budgets recounted. A zid once proven stays the appliance's."""
        for zid in set(self._own_graphs) - zids:
            self._own_graphs.pop(zid).undeclare()
        for zid in zids - set(self._own_graphs) - {self.zid}:
            self._own_graphs[zid] = self.session.liveliness().declare_subscriber(
                f"{rosgraph.ADMIN_SPACE}/{self.domain_id}/{zid}/**",
                zenoh.handlers.RingChannel(TOKEN_RING),
                history=True,
            )
        self.appliance |= zids
        self.per_session = {}
        for zid in self.owner.values():
            self.per_session[zid] = self.per_session.get(zid, 0) + 1
        self.foreign = sum(n for z, n in self.per_session.items() if z not in self.appliance)

    def wanted(self, key: str) -> bool:
        """Whether the data key is one of the recorder's ``topics``."""
        try:
            ke = zenoh.KeyExpr(key)
        except Exception:
            return False
        return any(sel.intersects(ke) for sel in self.selectors)

    def _subscribe(self, key: str) -> None:
        """Other sessions' samples of ``key``: the recorder's own come through ``own`` (the
        command log's key is every process' and its own, and came twice)."""
        if key not in self.subs:
            self.subs[key] = self.session.declare_subscriber(
                key, zenoh.handlers.RingChannel(self.ring), allowed_origin=zenoh.Locality.REMOTE
            )

    def samples(self) -> Iterator[Any]:
        """What the rings hold now: the bundles, then each topic's."""
        for sub in (self.bundles, *self.own, *self.subs.values()):
            while (sample := sub.try_recv()) is not None:
                yield sample

    def close(self) -> None:
        for sub in (
            self._graph,
            self._nodes,
            *self._own_graphs.values(),
            self._bundle_tokens,
            self.bundles,
            *self.own,
            *self.subs.values(),
        ):
            sub.undeclare()
        self.subs, self._own_graphs = {}, {}
