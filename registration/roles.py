"""The anatomical role each tracked body plays in the knee: the femur, the tibia or the patella.

A bone plays its own role; an implant component plays the bone it replaces (the femoral
component the femur, the tibial tray the tibia). The tracker orders, starts and carries bodies
by their roles, and the kinematics read the femur and the tibia by role, whatever the bodies
are called.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Literal, get_args

Role = Literal["femur", "tibia", "patella"]
"""A tracked body's anatomical role."""

ROLE_ORDER: tuple[Role, ...] = ("tibia", "femur", "patella")
"""The order bodies are registered in each frame, by role (largest and slowest first)."""

LONE_ROLES: tuple[Role, ...] = ("tibia", "femur")
"""Roles whose bodies a first frame searches alone (the rest of the scene still at its
starting estimate); the others are searched against them."""

CARRIED_BY: dict[Role, Role] = {"patella": "femur"}
"""A role whose motion is predicted relative to another's: the patella rides in the femur's
trochlea, so it is carried by the femur's new pose and extrapolated in the femur's frame."""

JOINED_TO: dict[Role, Role] = {"femur": "tibia", "tibia": "femur", "patella": "femur"}
"""The role whose body each role's body articulates with: a body lost between frames is
searched along its motion relative to that one (registration.priors.joint_screw)."""

KNOWN_ROLES: dict[str, Role] = {
    "femur": "femur",
    "tibia_fibula": "tibia",
    "tibia": "tibia",
    "patella": "patella",
    "femoral_component": "femur",
    "tibial_tray": "tibia",
    "patellar_component": "patella",
}
"""The role of each body named as the pipeline names them: the bones a static scan's labels
give (registration.labels.BONE_UNITS) and the implant components."""

COMPONENT_NAMES: dict[Role, str] = {
    "femur": "femoral_component",
    "tibia": "tibial_tray",
    "patella": "patellar_component",
}
"""The name an implant component playing each role is tracked under."""


def roles_of(bodies: Iterable[str], given: Mapping[str, str] | None = None) -> dict[str, Role]:
    """Each body's role: as ``given``, else known by its name (:data:`KNOWN_ROLES`).

    Args:
        bodies: The tracked bodies' names.
        given: Roles by body name, for bodies named otherwise (a researcher's ``"tray_a"``).

    Returns:
        The role of every body, by name.

    Raises:
        ValueError: A body without a known role, a role that is none of :data:`Role`'s, or
            two bodies playing one role.

    Examples:
        >>> roles_of(["femoral_component", "tibial_tray"])
        {'femoral_component': 'femur', 'tibial_tray': 'tibia'}
        >>> roles_of(["tray_a"], {"tray_a": "tibia"})
        {'tray_a': 'tibia'}
    """
    given = dict(given or {})
    names = list(bodies)
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise ValueError(f"roles given for bodies not tracked: {unknown} (tracked: {names})")
    roles: dict[str, Role] = {}
    for name in names:
        role = given.get(name, KNOWN_ROLES.get(name))
        if role is None:
            raise ValueError(
                f"body {name!r} has no known role: name it after its role (one of "
                f"{sorted(KNOWN_ROLES)}) or give its role ({', '.join(get_args(Role))})"
            )
        if role not in get_args(Role):
            raise ValueError(f"body {name!r}: role {role!r}, one of {', '.join(get_args(Role))}")
        roles[name] = role
    taken: dict[str, str] = {}
    for name, role in roles.items():
        if role in taken:
            raise ValueError(f"bodies {taken[role]!r} and {name!r} both play the {role}")
        taken[role] = name
    return roles


def body_playing(role: Role, roles: Mapping[str, Role]) -> str | None:
    """The name of the body playing ``role`` among ``roles`` (:func:`roles_of`), or None.

    Examples:
        >>> body_playing("tibia", {"femur": "femur", "tibia_fibula": "tibia"})
        'tibia_fibula'
    """
    return next((name for name, r in roles.items() if r == role), None)


def tracking_order(roles: Mapping[str, Role]) -> tuple[str, ...]:
    """The bodies in the order a frame registers them (:data:`ROLE_ORDER`).

    Examples:
        >>> tracking_order({"patella": "patella", "femur": "femur", "tibia_fibula": "tibia"})
        ('tibia_fibula', 'femur', 'patella')
    """
    return tuple(sorted(roles, key=lambda name: ROLE_ORDER.index(roles[name])))


def carriers(roles: Mapping[str, Role]) -> dict[str, str]:
    """Each carried body's carrier, by name (:data:`CARRIED_BY`), when both are tracked.

    Examples:
        >>> carriers({"femur": "femur", "patella": "patella"})
        {'patella': 'femur'}
    """
    out = {}
    for name, role in roles.items():
        carrier = body_playing(CARRIED_BY[role], roles) if role in CARRIED_BY else None
        if carrier is not None:
            out[name] = carrier
    return out


def partners(roles: Mapping[str, Role]) -> dict[str, str]:
    """Each body's partner in the joint, by name (:data:`JOINED_TO`), when both are tracked.

    Examples:
        >>> partners({"femoral_component": "femur", "tibial_tray": "tibia"})
        {'femoral_component': 'tibial_tray', 'tibial_tray': 'femoral_component'}
    """
    out = {}
    for name, role in roles.items():
        partner = body_playing(JOINED_TO[role], roles)
        if partner is not None:
            out[name] = partner
    return out


def first_playing(role: Role, bodies: Iterable[str]) -> str | None:
    """The first of ``bodies`` (named as the pipeline names them) to play ``role`` in
    :data:`KNOWN_ROLES`' order (the bone units first), or None.

    Examples:
        >>> first_playing("tibia", ["tibia", "fibula", "tibia_fibula"])
        'tibia_fibula'
    """
    names = set(bodies)
    return next((n for n, r in KNOWN_ROLES.items() if r == role and n in names), None)


def playing(bodies: Iterable[str], *wanted: Role) -> tuple[str, ...]:
    """The names of the bodies playing each ``wanted`` role among ``bodies`` (named as the
    pipeline names them; others are passed over), in the order asked; where several play a
    role (a simulation's truth has the tibia, the fibula and their unit), the first
    (:func:`first_playing`).

    Raises:
        ValueError: No body plays a wanted role.

    Examples:
        >>> playing(["femoral_component", "tibial_tray"], "femur", "tibia")
        ('femoral_component', 'tibial_tray')
        >>> playing(["femur", "tibia", "fibula", "tibia_fibula", "patella"], "tibia")
        ('tibia_fibula',)
    """
    names = list(dict.fromkeys(bodies))
    found = []
    for role in wanted:
        name = first_playing(role, names)
        if name is None:
            raise ValueError(
                f"poses of {names}: no body plays the {role} (a {role}'s names: "
                f"{sorted(n for n, r in KNOWN_ROLES.items() if r == role)})"
            )
        found.append(name)
    return tuple(found)
