"""Who may do what on a run's bus: the access-control rules of the orchestrator's router.

Zenoh's own access control (the router's ``access_control`` section) enforces them, with
``default_permission = "deny"``: a message or declaration passes only when a rule of the
sender's (ingress) or receiver's (egress) principal allows it. Principals are the user names of
Zenoh's user/password authentication (:mod:`hilswarm.orchestrator.run_security` makes one per
agent and one for the operator). The instance manager and the recorder live in the router's
own process (its local session), which access control does not filter.

Per principal, a :class:`Grants` lists key expressions (under the run's prefix):

* ``put`` — it may publish there (and sees who subscribes there, so its publishers match);
* ``subscribe`` — it may subscribe there and receives what is published there;
* ``tokens`` — it may declare liveliness tokens there;
* ``watch_tokens`` — it may watch liveliness tokens there;
* ``queryables`` — it may answer queries there;
* ``query`` — it may send queries there and receives their replies.

What follows from the experiment (:func:`run_grants`):

* agent i: put ``agent/<i>/**``, tokens ``alive/<i>``, queryable ``agent/<i>/set``, subscribe
  ``tick``, ``control`` and ``agent/<j>/y`` for exactly its graph neighbours j (the adjacency
  matrix enforced by the router), and its own ``agent/<i>/link/{rx,robot/in}`` (a board behind
  the XBee gateway), watch ``alive/_manager`` and its own ``alive/<i>`` (a second process
  for the same agent is refused at start), query its own ``agent/<i>/flush`` (answered by
  no one: :func:`hilswarm.agents.bus.flush_barrier`);
* operator (``hilswarm stop`` / ``set``): put ``manager/request`` (and ``gateway/sim``, fault
  commands to a simulated XBee coordinator), subscribe ``manager/status``, query
  ``agent/*/set``;
* viewer (live views, tools): subscribe everything, watch every token, put nothing;
* only the manager (local) puts ``tick`` and ``control``.

Other processes the orchestrator starts get principals of their own through ``extra``:
:data:`MOCAP_GRANTS` (the mocap process and its simulator: put ``mocap/**``,
``mocap_status`` and ``mocap_clock``, hear ``mocap_truth/**``) and :data:`GATEWAY_GRANTS`
(the XBee gateway: put and subscribe ``agent/*/link/**``, put ``gateway/{status,stats}``, hear
``gateway/sim``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from hilswarm.agents import bus

#: Liveliness name of the instance manager (as in :data:`hilswarm.agents.agent.MANAGER_NAME`).
MANAGER_TOKEN = "_manager"
#: User name of the operator principal (``hilswarm stop``, ``hilswarm set``).
OPERATOR = "operator"


def agent_user(name: str) -> str:
    """User name of agent ``name``'s principal."""
    return f"agent.{bus.check_key_name(name, what='agent name')}"


@dataclass(frozen=True)
class Grants:
    """What one principal may do; key expressions relative to the run's prefix."""

    put: tuple[str, ...] = ()
    subscribe: tuple[str, ...] = ()
    tokens: tuple[str, ...] = ()
    watch_tokens: tuple[str, ...] = ()
    queryables: tuple[str, ...] = ()
    query: tuple[str, ...] = ()


#: User name of the viewer principal: reads everything of the run (live views, tools, tests).
VIEWER = "viewer"
#: The viewer: subscribes to every key of the run and watches every liveliness token.
VIEWER_GRANTS = Grants(subscribe=("**",), watch_tokens=("alive/*",))
#: User name of the motion-capture principal (the mocap process and its simulator).
MOCAP = "mocap"
#: The motion-capture processes: publish poses under ``mocap/``, their status and the frame
#: clock (read by the manager, which the router does not filter, and viewers); the simulator
#: hears the simulated plants' true poses; the mocap process hears the tick key (the manager's
#: schedule says which frames the ticks use, :mod:`hilswarm.agents.mocap.decimation`).
MOCAP_GRANTS = Grants(
    put=("mocap/**", "mocap_status", "mocap_clock"),
    subscribe=("mocap_truth/**", "tick"),
    tokens=("alive/_mocap",),
)
#: User name of the XBee gateway principal.
GATEWAY = "gateway"
#: The radio gateway: relays agents' link traffic both ways, announces its state.
GATEWAY_GRANTS = Grants(
    put=("agent/*/link/**", "gateway/status", "gateway/stats"),
    subscribe=("agent/*/link/**", "gateway/sim"),
)


def agent_grants(
    name: str, neighbours: Sequence[str], bodies: Mapping[str, str] | None = None
) -> Grants:
    """Grants of agent ``name`` hearing ``neighbours`` (its row of the adjacency matrix).

    ``bodies`` (agent -> mocap rigid body, with ``[mocap]``): it also hears its own body's
    and its neighbours' bodies' poses and the mocap status, and puts its simulated plant's
    true pose (for the mocap simulator).
    """
    bus.check_key_name(name, what="agent name")
    mocap_put: tuple[str, ...] = ()
    mocap_sub: tuple[str, ...] = ()
    if bodies:
        mocap_put = (f"mocap_truth/{bodies[name]}",)
        mocap_sub = ("mocap_status", *(f"mocap/{bodies[n]}" for n in (name, *neighbours)))
    return Grants(
        put=(f"agent/{name}/**", *mocap_put),
        subscribe=(
            "tick",
            "control",
            *(f"agent/{j}/y" for j in neighbours),
            # its board behind the XBee gateway, and the UART of its simulated robot there
            f"agent/{name}/link/rx",
            f"agent/{name}/link/robot/in",
            *mocap_sub,
        ),
        tokens=(f"alive/{name}",),
        # its own token too: at start it asks whether another process runs it already
        watch_tokens=(f"alive/{MANAGER_TOKEN}", f"alive/{name}"),
        queryables=(f"agent/{name}/set",),
        # the query no one answers before it closes its session (bus.flush_barrier)
        query=(f"agent/{name}/flush",),
    )


#: The operator: commands to the manager, the manager's state, parameter changes, fault
#: commands to a simulated XBee coordinator (``gateway/sim``).
OPERATOR_GRANTS = Grants(
    put=("manager/request", "gateway/sim"),
    subscribe=("manager/status",),
    query=("agent/*/set",),
)


def run_grants(
    neighbours: Mapping[str, Sequence[str]],
    extra: Mapping[str, Grants] | None = None,
    bodies: Mapping[str, str] | None = None,
) -> dict[str, Grants]:
    """Every principal of a run: one per agent (``neighbours``: agent -> who it hears;
    ``bodies``: agent -> mocap body, with ``[mocap]``), the operator, and ``extra`` (user name
    -> grants)."""
    grants = {
        agent_user(name): agent_grants(name, heard, bodies) for name, heard in neighbours.items()
    }
    grants[OPERATOR] = OPERATOR_GRANTS
    grants.update(extra or {})
    return grants


# (messages, flow) per grant field; ingress: from the principal, egress: to it.
_RULES: dict[str, tuple[tuple[tuple[str, ...], str], ...]] = {
    "put": ((("put",), "ingress"), (("declare_subscriber",), "egress")),
    "subscribe": ((("declare_subscriber",), "ingress"), (("put",), "egress")),
    "tokens": ((("liveliness_token",), "ingress"),),
    "watch_tokens": (
        (("declare_liveliness_subscriber", "liveliness_query"), "ingress"),
        (("liveliness_token", "reply"), "egress"),
    ),
    "queryables": (
        (("declare_queryable", "reply"), "ingress"),
        (("query",), "egress"),
    ),
    "query": ((("query",), "ingress"), (("declare_queryable", "reply"), "egress")),
}


def access_control(keys: bus.BusKeys, grants: Mapping[str, Grants]) -> dict[str, Any]:
    """Zenoh's ``access_control`` section for a run: default deny, ``grants`` allowed.

    Args:
        keys: the run's keys (its prefix heads every key expression).
        grants: user name -> what it may do.
    """
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for user, grant in grants.items():
        rule_ids = []
        for field, patterns in vars(grant).items():
            if not patterns:
                continue
            key_exprs = [f"{keys.prefix}/{pattern}" for pattern in patterns]
            for n, (messages, flow) in enumerate(_RULES[field]):
                rule_id = f"{user}/{field}/{n}"
                rules.append(
                    {
                        "id": rule_id,
                        "messages": list(messages),
                        "flows": [flow],
                        "permission": "allow",
                        "key_exprs": key_exprs,
                    }
                )
                rule_ids.append(rule_id)
        subjects.append({"id": user, "usernames": [user]})
        policies.append({"id": user, "rules": rule_ids, "subjects": [user]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
