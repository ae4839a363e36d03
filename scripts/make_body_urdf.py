#!/usr/bin/env python
"""Write configs/body.urdf: the human body chain for a 1.75 m subject (regenerate after editing the tables); with
``--markers``, configs/body_markers.urdf, the marker tracker's skeleton: the same with a shoulder girdle and an
ankle that inverts.

    .venv/bin/python scripts/make_body_urdf.py [OUT] [--markers]

Rest pose (all angles zero): standing upright, facing +X, left towards +Y, arms hanging down; the root
translation is the pelvis (mid-hip) position, so a standing subject has root_tz = 0.93 (see meta in the file).
Spherical joints are ensembles of 1-DOF revolute joints, parent to child: flexion (about the lateral axis),
abduction (about the forward axis), twist (about the bone). Signs are chosen so that positive values are
flexion / abduction for both sides.
"""

from __future__ import annotations

import sys
from pathlib import Path

PI = 3.14159265

# Root: 3 prismatic + 3 revolute (yaw, pitch, roll) from the world origin to the pelvis link.
ROOT_DOFS = [
    ("root_tx", "prismatic", (1, 0, 0), (-50.0, 50.0)),
    ("root_ty", "prismatic", (0, 1, 0), (-50.0, 50.0)),
    ("root_tz", "prismatic", (0, 0, 1), (-50.0, 50.0)),
    # Root rotations are unbounded in practice; the wide limit keeps the URDF a plain revolute chain.
    ("root_rz", "revolute", (0, 0, 1), (-100.0, 100.0)),
    ("root_ry", "revolute", (0, 1, 0), (-100.0, 100.0)),
    ("root_rx", "revolute", (1, 0, 0), (-100.0, 100.0)),
]

# Bones: (bone link, parent bone link, joint origin in the parent bone's frame (m), dofs).
# dofs: (name, axis, (lower, upper)) in parent-to-child order.
BONES = [
    ("torso", "pelvis", (0.0, 0.0, 0.10), [
        ("spine_flex", (0, 1, 0), (-0.5, 1.3)),
        ("spine_abd", (1, 0, 0), (-0.6, 0.6)),
        ("spine_twist", (0, 0, 1), (-0.8, 0.8)),
    ]),
    ("head", "torso", (0.0, 0.0, 0.45), [
        ("neck_flex", (0, 1, 0), (-0.8, 1.0)),
        ("neck_abd", (1, 0, 0), (-0.6, 0.6)),
        ("neck_twist", (0, 0, 1), (-1.2, 1.2)),
    ]),
]
#: The shoulder girdle of the marker skeleton (``--markers``): the shoulder joint carried by a clavicle turning at
#: the sternoclavicular joint, a fifth of the way out to the shoulder (elevation about the forward axis,
#: protraction about the vertical).
GIRDLE_MEDIAL = 0.2
GIRDLE = [(f"{side}_clavicle", "torso", (0.0, s * 0.19 * GIRDLE_MEDIAL, 0.38), [
    (f"{side}_shoulder_elev", (s, 0, 0), (-0.2, 0.5)),
    (f"{side}_shoulder_prot", (0, 0, -s), (-0.4, 0.4)),
]) for side, s in (("l", 1), ("r", -1))]
#: The marker skeleton's ankle: after the flexion, inversion (about the forward axis; positive turns the sole towards
#: the midline), which a foot's heel, toe and metatarsal markers show; within a quarter radian, about a foot's range
#: in gait (docs/results.md, "Marker-based capture").
FOOT = {side: [(f"{side}_ankle_inv", (-s, 0, 0), (-0.25, 0.25))] for side, s in (("l", 1), ("r", -1))}
for side, s in (("l", 1), ("r", -1)):
    BONES += [
        (f"{side}_upperarm", "torso", (0.0, s * 0.19, 0.38), [
            (f"{side}_shoulder_flex", (0, -1, 0), (-1.0, 3.1)),
            (f"{side}_shoulder_abd", (s, 0, 0), (-0.3, 3.1)),
            (f"{side}_shoulder_twist", (0, 0, s), (-1.5, 1.5)),
        ]),
        (f"{side}_forearm", f"{side}_upperarm", (0.0, 0.0, -0.29), [
            (f"{side}_elbow_flex", (0, -1, 0), (0.0, 2.6)),
        ]),
        (f"{side}_hand", f"{side}_forearm", (0.0, 0.0, -0.25), [
            (f"{side}_wrist_flex", (0, 1, 0), (-1.2, 1.2)),
        ]),
        (f"{side}_thigh", "pelvis", (0.0, s * 0.09, 0.0), [
            (f"{side}_hip_flex", (0, -1, 0), (-0.5, 2.2)),
            (f"{side}_hip_abd", (s, 0, 0), (-0.5, 1.0)),
            (f"{side}_hip_twist", (0, 0, s), (-0.8, 0.8)),
        ]),
        (f"{side}_shank", f"{side}_thigh", (0.0, 0.0, -0.42), [
            (f"{side}_knee_flex", (0, 1, 0), (0.0, 2.6)),
        ]),
        (f"{side}_foot", f"{side}_shank", (0.0, 0.0, -0.42), [
            (f"{side}_ankle_flex", (0, -1, 0), (-0.9, 0.5)),
        ]),
    ]

# Fixed points (landmarks and bone ends): (link, parent bone link, origin in the parent's frame).
SITES = [
    ("thorax", "torso", (0.0, 0.0, 0.22)),
    ("head_center", "head", (0.0, 0.0, 0.15)),
    ("head_top", "head", (0.0, 0.0, 0.27)),
]
for side, s in (("l", 1), ("r", -1)):
    SITES += [
        (f"{side}_hand_tip", f"{side}_hand", (0.0, 0.0, -0.09)),
        (f"{side}_toe", f"{side}_foot", (0.15, 0.0, -0.09)),
    ]


def _f(v) -> str:
    return " ".join(f"{x:g}" for x in v)


def _joint(name, kind, parent, child, xyz=(0, 0, 0), axis=None, limits=None) -> str:
    out = [f'  <joint name="{name}" type="{kind}">',
           f'    <parent link="{parent}"/>', f'    <child link="{child}"/>',
           f'    <origin xyz="{_f(xyz)}" rpy="0 0 0"/>']
    if axis is not None:
        out.append(f'    <axis xyz="{_f(axis)}"/>')
    if limits is not None:
        out.append(f'    <limit lower="{limits[0]:g}" upper="{limits[1]:g}" effort="100" velocity="10"/>')
    out.append("  </joint>")
    return "\n".join(out)


def _bones(markers: bool) -> list:
    """BONES, or with ``markers`` each upper arm hung from the outer end of a clavicle listed just before it and each
    foot with the ankle's inversion."""
    if not markers:
        return BONES
    out = []
    for b, p, xyz, d in BONES:
        if b.endswith("_foot"):
            d = d + FOOT[b[0]]
        if b.endswith("_upperarm"):
            out += [c for c in GIRDLE if c[0] == f"{b[0]}_clavicle"]
            xyz, p = (0.0, xyz[1] * (1 - GIRDLE_MEDIAL), 0.0), f"{b[0]}_clavicle"
        out.append((b, p, xyz, d))
    return out


def build(markers: bool = False) -> str:
    """The URDF text of the body (``markers``: the marker skeleton, with the shoulder girdle and the ankle's
    inversion)."""
    links = ["world"]
    joints = []
    parent = "world"
    for i, (name, kind, axis, lim) in enumerate(ROOT_DOFS):
        child = "pelvis" if i == len(ROOT_DOFS) - 1 else f"{name}_link"
        links.append(child)
        joints.append(_joint(name, kind, parent, child, axis=axis, limits=lim))
        parent = child
    for bone, parent_bone, xyz, dofs in _bones(markers):
        parent = parent_bone
        for i, (name, axis, lim) in enumerate(dofs):
            child = bone if i == len(dofs) - 1 else f"{name}_link"
            links.append(child)
            joints.append(_joint(name, "revolute", parent, child, xyz=xyz if i == 0 else (0, 0, 0),
                                 axis=axis, limits=lim))
            parent = child
    for site, parent_bone, xyz in SITES:
        links.append(site)
        joints.append(_joint(f"{site}_fixed", "fixed", parent_bone, site, xyz=xyz))
    body = "\n".join([f'  <link name="{n}"/>' for n in links] + joints)
    return ('<?xml version="1.0"?>\n'
            "<!-- Generated by scripts/make_body_urdf.py; edit the tables there. Z up, facing +X, metres.\n"
            "     Standing root height (pelvis above the soles): 0.93 m; subject height 1.75 m. -->\n"
            f'<robot name="torchtrack_body">\n{body}\n</robot>\n')


if __name__ == "__main__":
    markers = "--markers" in sys.argv[1:]
    args = [a for a in sys.argv[1:] if a != "--markers"]
    name = "body_markers.urdf" if markers else "body.urdf"
    out = Path(args[0]) if args else Path(__file__).resolve().parents[1] / "configs" / name
    out.write_text(build(markers))
    print(f"wrote {out}")
