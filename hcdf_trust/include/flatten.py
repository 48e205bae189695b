"""Flatten a resolved include tree into one self-contained HCDF document.

:func:`flatten` expands every ``<include>`` recursively (nested includes compose)
and returns UTF-8 bytes with an XML declaration. It decides everything from the
:class:`~hcdf_trust.include.resolver.Resolution`; it reads no file and opens no socket.

Conventions this module defines (HCDF 1.0 leaves them to tooling):

Name prefix
    An include's ``name`` becomes a prefix joined with ``_`` (:data:`SEPARATOR`):
    ``<include name="left_arm">`` turns comp ``base`` into ``left_arm_base``. Not
    ``/`` or ``.``: HCDF already uses both to split ``comp/port`` and ``comp.motor``
    references, so a prefixed name must contain neither, and an include ``name``
    containing ``/``, ``.`` or white space is refused. ``_`` is also the house
    style of HCDF names (``left_shoulder``, ``wheel_fl_motor_driver``). The
    including document refers to an included comp by its prefixed name
    (``<child comp="left_arm_base"/>``). Nested prefixes compose outer first
    (``robot_left_arm_hand_palm``). An include without ``name`` adds no prefix.

    Prefixed: the document-level names (``comp``, ``joint``, ``group``, ``state``,
    ``network``, ``transmission``, ``material``) and the network-level names
    (``link``, ``bus``, ``chain``, ``schedule``, ``mesh``) defined by the included
    file, and every reference to them: joint ``parent``/``child`` comp, ``mimic``
    joint, group ``joint``/``group`` refs and ``tip-comp``, ``joint-position``
    joint, self-collision ``pair`` comp1/comp2, transmission ``joint`` ref,
    ``surface material`` and visual ``material name``, the comp part of
    ``comp/port`` and ``comp.port`` paths (wired ``<port>``, wireless
    ``<antenna>``, schedule ``assign ports``), ``device`` of bus participants,
    PLCA coordinators, chain hops, spurs, gPTP clocks and mesh nodes, tunnel
    ``hop``/``chain``, DC ``reference-clock``, ``assign schedule``/``chains``, and a
    frame's ``relative-to`` when it names a comp rather than a sibling frame.

    Not prefixed: names that live inside one comp (port, sensor, motor, visual,
    collision, frame, antenna, surface, hmi, power-source, software). Their comp
    already carries the prefix, and the references to them are either
    comp-qualified (``comp/port``) or implicitly on the same comp (motor
    ``encoder``, port ``visual``, group ``tip-frame``). A transmission's bare motor
    or encoder reference (``<motor ref="foc_motor"/>``), which is unambiguous only
    inside its own file, is qualified with its comp in the schema's dotted form
    (``left_arm_base.foc_motor``) when exactly one comp of the included file has
    that motor (or sensor). Opaque strings are left as written: MACsec
    ``key-ref``, ``key-store ref``, ``software name``, power-source ``group``,
    visual ``toggle``, and everything inside ``<extension>``. A reference to a name
    the included file does not define is left as written, so a sub-assembly may
    refer to its includer's names. Stream-profile files are pinned artifacts and
    are not rewritten: a profile inside an included file still names the
    unprefixed comps.

Pose
    HCDF 1.0 comps have no pose. The flattened output places each top-level comp
    of an included file (a comp that is the child of no joint in that file, after
    its own includes are expanded) with a ``<pose>x y z roll pitch yaw</pose>``
    first child: meters and radians, fixed-axis roll-pitch-yaw as in URDF/SDF,
    ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``, relative to the including document's
    frame. The include's ``pose`` is composed onto any ``<pose>`` the comp already
    has (include ∘ comp), so nested includes compose outer ∘ inner. Numbers are
    written with 15 significant digits, values under 1e-12 as ``0``. An include
    without ``pose`` leaves its comps' poses as they are. If the including file
    also attaches such a comp with a joint, the joint governs its placement and
    the pose is informational. A document with a comp ``<pose>`` is not valid
    against the HCDF 1.0 XSD (whose comp has no pose): the price of keeping the
    include offsets.

Frames
    Every file in the include tree that declares ``body-frame`` or
    ``world-frame`` must declare the value the first declaring file (root first,
    then includes depth first) declared; a file that omits one inherits it. The
    agreed values are written on the output root even when only an included file
    declared them.

Output
    The root's attributes, namespaces, metadata (description, author, license,
    url) and the comments around its elements are kept; included files'
    metadata are dropped and recorded in one provenance comment (prefix, file,
    sha256, module name, author, license, pose). Top-level elements appear in the
    schema's order (comp, joint, group, state, self-collision-disable, network,
    transmission, material), the root's own first, then each include's in
    document order; elements the schema does not know come last. All
    ``self-collision-disable`` pairs are merged into one element (the schema
    allows one). A comment directly before an element in an included file moves
    with it. Relative file references (model, mesh, stream profile, firmware
    manifest) that resolved against their own document are rewritten relative
    to the output's folder; references resolved against ``--base`` are kept as
    written. Indentation is regenerated. The same inputs give byte-identical output.

Root
    The output resolves again with the run's ``--root``/``--base``: every local file
    it references must lie inside ``--root`` (else a local ``--base``), or, when the
    run names neither, inside the output's own folder, where a plain ``resolve`` of
    it confines its references. Otherwise flattening is refused before anything is
    written, naming the first reference that would leave and the two ways out.

Bounds
    :func:`expanded_elements` counts the output's elements from the include graph
    alone (times each document is expanded × its elements, exact big integers), and
    more than ``max_elements`` (:data:`DEFAULT_MAX_ELEMENTS`) is refused before any
    copying. Every walk (:func:`include_order`, the expansion, the provenance tree) is
    iterative, so include chains as deep as ``--max-depth`` allows never recurse.
"""

from __future__ import annotations

import copy
import math
import os
import posixpath
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from urllib.parse import unquote, urljoin, urlsplit

from lxml import etree

from ..document import URI_ATTRS, Document, Kind
from ..errors import FlattenError, counted
from ..localfile import absolute
from ..xml import MAX_ELEMENTS, sourceline
from .locate import _normalise, display_path, file_url
from .resolver import Resolution, display_url

__all__ = [
    "DEFAULT_MAX_ELEMENTS",
    "SEPARATOR",
    "Pose",
    "expanded_elements",
    "flatten",
    "format_pose",
    "include_order",
    "parse_pose",
]

SEPARATOR = "_"
#: The most elements a flattened document may have unless ``--max-elements`` raises it.
#: About 20 MB of output, 360 MB of memory and 5 s here; the published humanoid has about 2,000.
DEFAULT_MAX_ELEMENTS = MAX_ELEMENTS

#: Names defined at document level, in the schema's order of <hcdf> children.
DOCUMENT_KINDS = ("comp", "joint", "group", "state", "network", "transmission", "material")
#: Names defined inside a <network>.
NETWORK_KINDS = ("link", "bus", "chain", "schedule", "mesh")
METADATA = ("description", "author", "license", "url")
SECTIONS = (
    *METADATA,
    "comp",
    "joint",
    "group",
    "state",
    "self-collision-disable",
    "network",
    "transmission",
    "material",
)
_UNKNOWN_SECTION = len(SECTIONS)
_FORBIDDEN_IN_PREFIX = ("/", ".")

# Elements whose ``device`` attribute names a comp (bus, PLCA, chain, spur, gPTP, mesh).
_DEVICE_TAGS = frozenset({"participant", "coordinator", "hop", "spur", "clock", "node"})
# Every element :func:`_rename_references` may rename something in.
_REFERRING = frozenset(
    {
        *("parent", "child", "mimic", "group", "joint", "joint-position", "pair", "motor", "spring"),
        *("transmission", "surface", "material", "frame", "tunnel", "dc", "assign", "port", "antenna"),
        *_DEVICE_TAGS,
    }
)
_REFERRING_PATTERNS = tuple(sorted("{*}" + tag for tag in _REFERRING))

Matrix = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
Vector = tuple[float, float, float]


# --- rigid transforms ------------------------------------------------------------------


@dataclass(frozen=True)
class Pose:
    """A rigid transform: rotation matrix ``r`` then translation ``t`` (x = R·p + t)."""

    r: Matrix
    t: Vector

    @classmethod
    def identity(cls) -> Pose:
        return cls(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), (0.0, 0.0, 0.0))

    @classmethod
    def from_xyz_rpy(cls, x: float, y: float, z: float, roll: float, pitch: float, yaw: float) -> Pose:
        """``R = Rz(yaw)·Ry(pitch)·Rx(roll)`` (fixed axes X, Y, Z, as URDF/SDF)."""
        cr, sr = math.cos(roll), math.sin(roll)
        cp, sp = math.cos(pitch), math.sin(pitch)
        cy, sy = math.cos(yaw), math.sin(yaw)
        r = (
            (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
            (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
            (-sp, cp * sr, cp * cr),
        )
        return cls(r, (x, y, z))

    def compose(self, inner: Pose) -> Pose:
        """``self ∘ inner``: apply ``inner`` first, then ``self``."""
        (a0, a1, a2), (b0, b1, b2), (v0, v1, v2) = self.r, inner.r, inner.t

        def row(a: Vector) -> Vector:
            return (
                a[0] * b0[0] + a[1] * b1[0] + a[2] * b2[0],
                a[0] * b0[1] + a[1] * b1[1] + a[2] * b2[1],
                a[0] * b0[2] + a[1] * b1[2] + a[2] * b2[2],
            )

        t0, t1, t2 = self.t
        return Pose(
            (row(a0), row(a1), row(a2)),
            (
                a0[0] * v0 + a0[1] * v1 + a0[2] * v2 + t0,
                a1[0] * v0 + a1[1] * v1 + a1[2] * v2 + t1,
                a2[0] * v0 + a2[1] * v1 + a2[2] * v2 + t2,
            ),
        )

    def rpy(self) -> Vector:
        """Roll, pitch, yaw with pitch in [-π/2, π/2]; stable near gimbal lock.

        Yaw and pitch come from the first column; roll from what is left once they
        are undone, so an error in yaw near gimbal lock is absorbed by roll instead
        of showing in the rotation.
        """
        r = self.r
        cp = math.hypot(r[0][0], r[1][0])
        pitch = math.atan2(-r[2][0], cp)
        yaw = math.atan2(r[1][0], r[0][0]) if cp > 1e-12 else math.atan2(-r[0][1], r[1][1])
        # M = Ry(pitch)^T · Rz(yaw)^T · R should be Rx(roll).
        inv = Pose.from_xyz_rpy(0, 0, 0, 0, pitch, yaw).r

        def m(i: int, j: int) -> float:
            return inv[0][i] * r[0][j] + inv[1][i] * r[1][j] + inv[2][i] * r[2][j]

        roll = math.atan2(m(2, 1) - m(1, 2), m(1, 1) + m(2, 2))
        return (roll, pitch, yaw)


# An xs:double written as digits (float() also takes "1_0", "\u0661" and "inf"), and
# the XML whitespace that separates the items of a list (str.split() takes any Unicode space).
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_XML_SPACE = re.compile(r"[ \t\r\n]+")


def parse_pose(text: str, *, file: str | None = None, line: int | None = None) -> Pose:
    """Parse ``"x y z roll pitch yaw"``: six numbers as an XML reader reads them.

    Raises:
        FlattenError: not six finite numbers.
    """
    parts = _XML_SPACE.split(text.strip(" \t\r\n"))
    values = [float(p) for p in parts if _DECIMAL.fullmatch(p)]
    if len(parts) != 6 or len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise FlattenError(
            f'pose {text.strip()!r} is not six numbers "x y z roll pitch yaw"',
            file=file,
            line=line,
            expected="x y z roll pitch yaw",
            actual=text.strip(),
        )
    return Pose.from_xyz_rpy(*values)


def _number(v: float) -> str:
    if abs(v) < 1e-12:
        return "0"
    return format(v, ".15g")


def format_pose(pose: Pose) -> str:
    return " ".join(_number(v) for v in (*pose.t, *pose.rpy()))


# --- the flattener ---------------------------------------------------------------------


#: Include names as a linked list, outermost first: prepending an outer name is O(1),
#: so a deep chain does not rebuild a tuple per level.
_Chain = tuple[str, "_Chain"] | None


def _unchain(chain: _Chain) -> tuple[str, ...]:
    out = []
    while chain is not None:
        name, chain = chain
        out.append(name)
    return tuple(out)


@dataclass
class _Item:
    """One top-level element of the flattened document, with where it was defined.

    ``pose`` is the placement composed so far (written as ``<pose>`` when serialised,
    so a deep chain composes transforms, not text); ``refs`` caches the elements that
    may refer to a name, found once per copy.
    """

    el: etree._Element
    source: str
    line: int | None
    comments: list[etree._Element] = field(default_factory=list)
    via: _Chain = None  # include names it came through, outermost first
    original: str | None = None  # its name before prefixing
    pose: Pose | None = None
    tag: str | None = None
    name: str | None = None  # its current name (written back to the element by _serialize)
    refs: list[etree._Element] | None = None
    inner: tuple[frozenset[str], tuple[tuple[str, str], ...]] | None = None  # frames; motors and sensors

    def __post_init__(self) -> None:
        if self.tag is None:
            self.tag = _local(self.el)
        if self.name is None:
            self.name = self.el.get("name")

    def copy(self) -> _Item:
        return _Item(
            copy.deepcopy(self.el),
            self.source,
            self.line,
            [copy.deepcopy(c) for c in self.comments],
            self.via,
            self.original,
            self.pose,
            self.tag,
            self.name,
            None,
            self.inner,
        )

    def references(self) -> list[etree._Element]:
        """The elements of this item that may name a comp, joint, ... (not inside ``<extension>``)."""
        if self.refs is None:
            el = self.el
            if self.tag == "extension" or el.find(".//{*}extension") is not None:
                self.refs = [e for e in _walk(el) if _local(e) in _REFERRING]
            else:
                self.refs = list(el.iter(*_REFERRING_PATTERNS))
        return self.refs

    def names_inside(self) -> tuple[frozenset[str], tuple[tuple[str, str], ...]]:
        """A comp's frame names, and its (motor|sensor, name) children: never prefixed."""
        if self.inner is None:
            frames = frozenset(frame for f in self.el if _local(f) == "frame" and (frame := f.get("name")))
            owned = tuple(
                (kind, child_name)
                for child in self.el
                if (kind := _local(child)) in ("motor", "sensor") and (child_name := child.get("name"))
            )
            self.inner = (frames, owned)
        return self.inner


@dataclass
class _Included:
    """One include site, for the provenance comment."""

    where: str
    target: str
    sha256: str | None
    module: str | None
    author: str | None
    license: str | None
    pose: str | None


@dataclass(frozen=True)
class _Site:
    """An include site and the sites of the file it includes: a tree, so that including
    an expansion one level further up adds one node instead of renaming every site below."""

    name: str  # the include's name ("" for none)
    included: _Included
    below: list[_Site]


@dataclass
class _Expansion:
    items: list[_Item]
    included: list[_Site]

    def copy(self) -> _Expansion:
        return _Expansion([i.copy() for i in self.items], list(self.included))


def flatten(
    res: Resolution,
    *,
    out_path: str | os.PathLike[str] | None = None,
    root: str | os.PathLike[str] | None = None,
    base: str | None = None,
    max_elements: int = DEFAULT_MAX_ELEMENTS,
) -> bytes:
    """One self-contained HCDF document with every include of ``res`` expanded.

    Relative file references are rewritten to hold from ``out_path``'s folder
    (default: the root document's folder). ``root`` and ``base`` are the run's
    ``--root`` and ``--base``: the flattened document resolves again with the same
    ones, so every local file it references must lie inside the folder they give
    it (``root``, else a local ``base``, else its own folder). ``max_elements`` caps
    :func:`expanded_elements`, checked before anything is copied.

    Raises:
        FlattenError: the tree has unresolved errors, is larger than ``max_elements``
            once expanded, references a file outside the flattened document's root,
            frames disagree, an include ``name`` or ``pose`` is unusable, an include
            is not a child of ``<hcdf>``, or two elements of one kind share a name
            after prefixing.
    """
    if not res.ok:
        raise FlattenError(
            "cannot flatten a document tree that did not resolve cleanly",
            file=res.root.source,
        )
    return _Flattener(res, out_path, root=root, base=base, max_elements=max_elements).run()


def include_order(res: Resolution) -> list[str]:
    """Every resolved document reachable from the root, each after all it includes
    (post-order, depth first in document order). Iterative: no recursion limit.

    Raises:
        FlattenError: an include cycle.
    """
    done: set[str] = set()
    on_stack: list[str] = [res.root_location.url]
    position = {res.root_location.url: 0}
    stack = [iter(res.includes.get(res.root_location.url, []))]
    order: list[str] = []
    while stack:
        for ref, child in stack[-1]:
            if child in done or child not in res.documents:
                continue
            if child in position:
                chain = " → ".join(display_url(u) for u in (*on_stack[position[child] :], child))
                raise FlattenError(f"include cycle: {chain}", file=display_url(on_stack[-1]), line=ref.line)
            position[child] = len(on_stack)
            on_stack.append(child)
            stack.append(iter(res.includes.get(child, [])))
            break
        else:
            stack.pop()
            url = on_stack.pop()
            del position[url]
            done.add(url)
            order.append(url)
    return order


def expanded_elements(res: Resolution, order: list[str] | None = None) -> tuple[int, str, int]:
    """How many elements the flattened document has, computed from the include graph
    alone: the sum over its documents of (times the document is expanded) × (its
    elements). Also the document contributing most and how often it is expanded.

    Raises:
        FlattenError: an include cycle.
    """
    order = include_order(res) if order is None else order
    instances = dict.fromkeys(order, 0)
    instances[res.root_location.url] = 1
    total, top, top_share = 0, res.root_location.url, -1
    for url in reversed(order):  # every includer before what it includes
        count = instances[url]
        share = count * sum(1 for _ in res.documents[url].root.iter(etree.Element))
        total += share
        if share > top_share:
            top, top_share = url, share
        for _, child in res.includes.get(url, []):
            if child in instances:
                instances[child] += count
    return total, top, instances[top]


def _count(n: int) -> str:
    return f"{n:,}" if n < 10**15 else f"about 10^{len(str(n)) - 1}"


class _Flattener:
    def __init__(
        self,
        res: Resolution,
        out_path: str | os.PathLike[str] | None = None,
        *,
        root: str | os.PathLike[str] | None = None,
        base: str | None = None,
        max_elements: int = DEFAULT_MAX_ELEMENTS,
    ) -> None:
        self.res = res
        self.root_url = res.root_location.url
        self.out_path = absolute(out_path) if out_path is not None else None
        self.target_url = file_url(self.out_path) if self.out_path is not None else self.root_url
        if root is None and base is not None and "://" not in base:
            root = base
        self.named_root = root is not None
        self.flat_root = absolute(root) if root is not None else posixpath.dirname(_path(self.target_url))
        self.max_elements = max_elements
        # Reference element -> (resolved URL, attribute or None for text).
        self.uri_of: dict[etree._Element, tuple[str, str | None]] = {}
        for art in res.artifacts.values():
            if art.kind is Kind.INCLUDE:
                continue
            for use in art.uses:
                if use.ref.element is not None:
                    self.uri_of[use.ref.element] = (art.url, use.ref.uri_attr)
        self.include_of: dict[str, dict[etree._Element, str]] = {
            url: {ref.element: child for ref, child in refs if ref.element is not None}
            for url, refs in res.includes.items()
        }

    def run(self) -> bytes:
        order = include_order(self.res)
        self._check_size(order)
        self._check_root()
        frames = self._check_frames()
        root_doc = self.res.documents[self.root_url]
        expansion = self._expand_all(order)
        _check_collisions(expansion.items)
        return _serialize(root_doc, expansion, frames)

    # -- bounds: checked before anything is copied -----------------------------------------

    def _check_size(self, order: list[str]) -> None:
        total, top, times = expanded_elements(self.res, order)
        if total <= self.max_elements:
            return
        raise FlattenError(
            f"the flattened document would have {_count(total)} elements, over the limit of "
            f"{self.max_elements:,} (raise it with --max-elements N); most come from "
            f"{display_url(top)}, expanded {_count(times)} times",
            file=self.res.root.source,
            expected=f"at most {self.max_elements:,} elements",
            actual=_count(total),
        )

    def _check_root(self) -> None:
        """Every local file the output references lies inside the folder it will be resolved in."""
        inside = self.flat_root.rstrip("/") + "/"
        outside = [
            art
            for art in self.res.artifacts.values()
            if art.kind is not Kind.INCLUDE
            and art.url.startswith("file://")
            and not (path := os.path.normpath(_path(art.url))).startswith(inside)
            and path != self.flat_root
        ]
        if not outside:
            return
        first = outside[0]
        use = first.uses[0]
        shown_root = display_path(self.flat_root)
        out = display_path(self.out_path) if self.out_path else self.res.root.source
        written = _relative_to_root(first.url, self.target_url)
        if self.named_root:
            why = f"outside --root {shown_root}"
        else:
            why = (
                f"outside its folder {shown_root}, the only folder a plain `hcdf-trust resolve {out}` lets it reference"
            )
        raise FlattenError(
            f"{out} would reference {counted(len(outside), 'file')} {why} (first {written}): write it beside "
            f"{self.res.root.source} or in a folder above, or give --root DIR (a folder holding both) "
            "to this run and to every run that reads the flattened document",
            file=use.doc,
            line=use.ref.line,
            expected=f"a file inside {shown_root}",
            actual=display_url(first.url),
        )

    # -- body-frame / world-frame --------------------------------------------------------
    def _check_frames(self) -> dict[str, str]:
        first: dict[str, tuple[str, str, int | None]] = {}
        seen: set[str] = set()
        stack = [self.root_url]
        while stack:
            url = stack.pop()
            if url in seen or url not in self.res.documents:
                continue
            seen.add(url)
            doc = self.res.documents[url]
            for attr in ("body-frame", "world-frame"):
                value = doc.root.get(attr)
                if value is None:
                    continue
                value = value.strip()
                if attr not in first:
                    first[attr] = (value, doc.source, sourceline(doc.root))
                    continue
                want, where, line = first[attr]
                if value != want:
                    raise FlattenError(
                        f'{attr} mismatch in the include chain: {where} declares {attr}="{want}" '
                        f'but {doc.source} declares {attr}="{value}" (every file in an include '
                        f"chain must use the same {attr})",
                        file=doc.source,
                        line=sourceline(doc.root),
                        expected=want,
                        actual=value,
                    )
            stack.extend(reversed([child for _, child in self.res.includes.get(url, [])]))
        return {attr: v[0] for attr, v in first.items()}

    # -- expansion -----------------------------------------------------------------------

    def _expand_all(self, order: list[str]) -> _Expansion:
        """The root with every include expanded, built leaves first (no recursion).

        Each document's expansion (its own names not yet prefixed) is kept until its
        last include site has taken it: earlier sites take a copy, the last one the
        original, so a chain holds about one copy at a time.
        """
        left: dict[str, int] = {}
        for url in order:
            for child in self.include_of.get(url, {}).values():
                if child in self.res.documents:
                    left[child] = left.get(child, 0) + 1
        memo: dict[str, _Expansion] = {}
        for url in order:
            memo[url] = self._expand(url, memo, left)
        return memo[self.root_url]

    def _take(self, url: str, memo: dict[str, _Expansion], left: dict[str, int]) -> _Expansion:
        left[url] -= 1
        return memo.pop(url) if left[url] == 0 else memo[url].copy()

    def _expand(self, url: str, memo: dict[str, _Expansion], left: dict[str, int]) -> _Expansion:
        """``url`` with its includes (already in ``memo``) expanded, its own names not prefixed."""
        doc = self.res.documents[url]
        is_root = url == self.root_url
        sites = self.include_of.get(url, {})
        for el in sites:
            parent = el.getparent()
            if parent is None or parent is not doc.root:
                raise FlattenError(
                    "<include> must be a child of <hcdf> to be flattened",
                    file=doc.source,
                    line=sourceline(el),
                )
        items: list[_Item] = []
        included: list[_Site] = []
        comments: list[etree._Element] = []
        for child in doc.root:
            if isinstance(child, etree._Comment):
                comments.append(copy.deepcopy(child))
                continue
            if not isinstance(child.tag, str):
                continue  # processing instructions, entities
            tag = etree.QName(child).localname
            if child in sites:
                child_url = sites[child]
                if child_url not in self.res.documents:
                    raise FlattenError(f"{display_url(child_url)} was not resolved", file=display_url(child_url))
                sub = self._include(doc, child, child_url, self._take(child_url, memo, left))
                items.extend(sub.items)
                included.extend(sub.included)
            elif tag == "include":
                raise FlattenError("<include> was not resolved", file=doc.source, line=sourceline(child))
            elif is_root or tag not in METADATA:
                copied = self._copy(doc, url, child)
                items.append(_Item(copied, doc.source, sourceline(child), comments))
            comments = []
        if is_root and comments:  # trailing comments of the root document
            items.append(_Item(etree.Element("_trailing"), doc.source, None, comments))
        return _Expansion(items, included)

    def _include(self, doc: Document, el: etree._Element, child_url: str, sub: _Expansion) -> _Expansion:
        """Prefix and place ``sub`` (``child_url`` expanded) as the include ``el`` asks."""
        name = (el.get("name") or "").strip()
        if any(c in name for c in _FORBIDDEN_IN_PREFIX) or any(c.isspace() for c in name):
            raise FlattenError(
                f"include name {name!r} cannot be a prefix: it may not contain '/', '.' or "
                f"white space (they separate comp/port and comp.element references)",
                file=doc.source,
                line=sourceline(el),
                expected="a name without '/', '.' or white space",
                actual=name,
            )
        pose_text = el.get("pose")
        pose = parse_pose(pose_text, file=doc.source, line=sourceline(el)) if pose_text else None
        if name:
            _prefix(sub.items, name)
        if pose is not None:
            _place(sub.items, pose)
        child = self.res.documents[child_url]
        art = self.res.artifacts.get(child_url)
        site = _Included(
            where=f"{doc.source}:{sourceline(el)}",
            target=_relative_to_root(child_url, self.root_url),
            sha256=art.sha256 if art is not None else None,
            module=child.root.get("name"),
            author=_text(child.root.find("author")),
            license=_text(child.root.find("license")),
            pose=pose_text.strip() if pose_text else None,
        )
        return _Expansion(sub.items, [_Site(name, site, sub.included)])

    def _copy(self, doc: Document, url: str, el: etree._Element) -> etree._Element:
        """A detached copy of ``el`` with its file references rebased onto the root."""
        out = copy.deepcopy(el)
        out.tail = None
        if url == self.target_url:
            return out
        for orig, new in zip(el.iter(), out.iter(), strict=True):
            found = self.uri_of.get(orig)
            if found is None:
                continue
            art_url, attr = found
            written = orig.get(attr) if attr else orig.text
            if written is None:
                continue
            rebased = _rebase(written, art_url, url, self.target_url)
            if rebased == written:
                continue
            if attr:
                for name in URI_ATTRS:  # uri and href both, when both are written (equal: document.py)
                    if orig.get(name) is not None:
                        new.set(name, rebased)
            else:
                new.text = rebased
        return out


def _text(el: etree._Element | None) -> str | None:
    if el is None or el.text is None:
        return None
    return " ".join(el.text.split()) or None


# --- file references ---------------------------------------------------------------------


def _rebase(uri: str, art_url: str, doc_url: str, root_url: str) -> str:
    """``uri`` written in ``doc_url`` and resolved to ``art_url``, as the root should write it."""
    text = uri.strip()
    if not text or urlsplit(text).scheme:
        return uri  # an absolute URL means the same everywhere
    if _normalise(urljoin(root_url, text)) == art_url:
        return uri
    if _normalise(urljoin(doc_url, text)) != art_url:
        return uri  # resolved against --base: means the same from any document
    return _relative_to_root(art_url, root_url)


def _path(url: str) -> str:
    return unquote(urlsplit(url).path)


def _relative_to_root(url: str, root_url: str) -> str:
    a, r = urlsplit(url), urlsplit(root_url)
    if (a.scheme, a.netloc) != (r.scheme, r.netloc) or a.query:
        return url
    return posixpath.relpath(a.path, posixpath.dirname(r.path))


# --- prefixing ---------------------------------------------------------------------------


def _local(el: etree._Element) -> str | None:
    tag = el.tag
    return tag.rpartition("}")[2] if isinstance(tag, str) else None


def _walk(el: etree._Element) -> Iterator[etree._Element]:
    """Every element under ``el`` (itself included), not entering ``<extension>``."""
    stack = [el]
    while stack:
        cur = stack.pop()
        if _local(cur) == "extension":
            continue
        yield cur
        stack.extend(reversed([c for c in cur if isinstance(c.tag, str)]))


class _Names:
    """The names one expansion defines, and how to rename references to them."""

    def __init__(self, items: list[_Item], prefix: str) -> None:
        self.prefix = prefix
        self.defined: dict[str, set[str]] = {k: set() for k in (*DOCUMENT_KINDS, *NETWORK_KINDS)}
        self.frames: dict[etree._Element, frozenset[str]] = {}  # comp element -> its frame names
        self.owners: dict[str, dict[str, list[str]]] = {"motor": {}, "sensor": {}}
        for item in items:
            tag = item.tag
            name = item.name
            if tag in DOCUMENT_KINDS and name is not None:
                self.defined[tag].add(name)
            if tag == "network":
                for child in item.el:
                    kind, child_name = _local(child), child.get("name")
                    if kind in NETWORK_KINDS and child_name is not None:
                        self.defined[kind].add(child_name)
            if tag == "comp" and name is not None:
                frames, owned = item.names_inside()
                self.frames[item.el] = frames
                for kind, child_name in owned:
                    self.owners[kind].setdefault(child_name, []).append(name)

    def new(self, kind: str, name: str) -> str:
        return f"{self.prefix}{SEPARATOR}{name}" if name in self.defined[kind] else name

    def path(self, value: str) -> str:
        """``comp``, ``comp/port`` or ``comp.element``: rename the longest known comp head."""
        text = value.strip()
        comps = self.defined["comp"]
        if text in comps:
            return self.new("comp", text)
        for i in range(len(text) - 1, 0, -1):
            if text[i] in "/." and text[:i] in comps:
                return self.new("comp", text[:i]) + text[i:]
        return value

    def qualified(self, value: str, kind: str) -> str:
        """A transmission's motor/encoder: dotted paths renamed, bare names qualified."""
        text = value.strip()
        if "." in text or "/" in text:
            return self.path(value)
        owners = self.owners[kind].get(text, [])
        if len(owners) == 1:
            return f"{self.new('comp', owners[0])}.{text}"
        return value

    def words(self, value: str, rename: Callable[[str], str]) -> str:
        words = value.split()
        renamed = [rename(w) for w in words]
        return " ".join(renamed) if renamed != words else value


def _prefix(items: list[_Item], prefix: str) -> None:
    """Prefix every name ``items`` define, and every reference to those names, in place."""
    names = _Names(items, prefix)
    for item in items:
        for el in item.references():
            _rename_references(el, names)
    for item in items:
        tag, name = item.tag, item.name
        if tag in DOCUMENT_KINDS and name is not None:
            if item.original is None:
                item.original = name
            item.name = names.new(tag, name)
        if tag == "network":
            for child in item.el:
                kind, child_name = _local(child), child.get("name")
                if kind in NETWORK_KINDS and child_name is not None:
                    child.set("name", names.new(kind, child_name))
        item.via = (prefix, item.via)


def _set(el: etree._Element, attr: str, rename: Callable[[str], str]) -> None:
    value = el.get(attr)
    if value is not None:
        new = rename(value)
        if new != value:
            el.set(attr, new)


def _rename_references(el: etree._Element, n: _Names) -> None:
    tag = _local(el)
    parent = el.getparent()
    ptag = _local(parent) if parent is not None else None

    def comp(v: str) -> str:
        return n.new("comp", v)

    if tag in ("parent", "child") and ptag == "joint":
        _set(el, "comp", comp)
    elif tag == "mimic":
        _set(el, "joint", lambda v: n.new("joint", v))
    elif tag == "group":
        if ptag == "group":
            _set(el, "ref", lambda v: n.new("group", v))
        else:
            _set(el, "tip-comp", comp)
    elif tag == "joint" and ptag in ("group", "transmission"):
        _set(el, "ref", lambda v: n.new("joint", v))
    elif tag == "joint-position":
        _set(el, "joint", lambda v: n.new("joint", v))
    elif tag == "pair":
        _set(el, "comp1", comp)
        _set(el, "comp2", comp)
    elif tag == "motor" and ptag == "transmission":
        _set(el, "ref", lambda v: n.qualified(v, "motor"))
    elif tag == "spring" and ptag == "transmission":
        _set(el, "equilibrium-actuator", lambda v: n.qualified(v, "motor"))
        _set(el, "stiffness-actuator", lambda v: n.qualified(v, "motor"))
    elif tag == "transmission":
        _set(el, "encoder", lambda v: n.qualified(v, "sensor"))
    elif tag == "surface":
        _set(el, "material", lambda v: n.new("material", v))
    elif tag == "material" and ptag == "visual":
        _set(el, "name", lambda v: n.new("material", v))
    elif tag == "frame" and ptag == "comp" and parent is not None:
        own = n.frames.get(parent, frozenset())
        _set(el, "relative-to", lambda v: v if v in own else comp(v))
    elif tag in _DEVICE_TAGS:
        _set(el, "device", comp)  # port, via, ingress, egress: port names on that device
    elif tag == "tunnel":
        _set(el, "hop", comp)
        _set(el, "chain", lambda v: n.new("chain", v))
    elif tag == "dc":
        _set(el, "reference-clock", comp)
    elif tag == "assign":
        _set(el, "schedule", lambda v: n.new("schedule", v))
        _set(el, "ports", lambda v: n.words(v, n.path))
        _set(el, "chains", lambda v: n.words(v, lambda w: n.new("chain", w)))
    elif (tag == "port" and ptag == "wired") or (tag == "antenna" and ptag == "wireless"):
        if el.text is not None:
            new = n.path(el.text)
            if new != el.text:
                el.text = new


# --- pose --------------------------------------------------------------------------------


def _place(items: list[_Item], pose: Pose) -> None:
    """Compose ``pose`` onto every comp of ``items`` that is the child of no joint.

    The first placement takes over the comp's own ``<pose>`` (removed here, written back
    composed by :func:`_serialize`).
    """
    children = set()
    for item in items:
        if item.tag == "joint":
            for c in item.el:
                if _local(c) == "child" and c.get("comp") is not None:
                    children.add(c.get("comp"))
    for item in items:
        if item.tag != "comp" or item.name in children:
            continue
        if item.pose is None:
            existing = [c for c in item.el if _local(c) == "pose"]
            inner = Pose.identity()
            if existing:
                line = sourceline(existing[0])
                inner = parse_pose(existing[0].text or "", file=item.source, line=line)
            for c in existing:
                item.el.remove(c)
            item.pose = inner
        item.pose = pose.compose(item.pose)


# --- collisions and output -------------------------------------------------------------------


def _check_collisions(items: list[_Item]) -> None:
    seen: dict[tuple[str, str], _Item] = {}
    for item in items:
        tag = item.tag
        name = item.name
        if tag not in DOCUMENT_KINDS or name is None:
            continue
        other = seen.setdefault((tag, name), item)
        if other is item:
            continue
        raise FlattenError(
            f'name collision after prefixing: <{tag} name="{name}"> is defined at '
            f"{_where(other)} and at {_where(item)}",
            file=item.source,
            line=item.line,
        )


def _where(item: _Item) -> str:
    text = f"{item.source}:{item.line}"
    if item.via:
        inc = ", ".join(repr(v) for v in _unchain(item.via))
        text += f' (as "{item.original}", included as {inc})'
    return text


def _comment_text(text: str) -> str:
    text = text.replace("--", "- -")
    return text + " " if text.endswith("-") else text


def _provenance(root: Document, included: list[_Site]) -> etree._Element:
    lines = [f" Flattened by hcdf-trust from {root.source}. Includes expanded:"]
    pending: list[tuple[_Site, tuple[str, ...]]] = [(site, ()) for site in reversed(included)]
    while pending:  # depth first, each site before the sites of the file it includes
        site, above = pending.pop()
        names = (*above, site.name) if site.name else above
        pending.extend((below, names) for below in reversed(site.below))
        inc = site.included
        prefix = SEPARATOR.join(names) if names else "(no prefix)"
        parts = [inc.target]
        if inc.sha256:
            parts.append(f"sha256 {inc.sha256}")
        if inc.module:
            parts.append(f'module "{inc.module}"')
        if inc.author:
            parts.append(f'author "{inc.author}"')
        if inc.license:
            parts.append(f'license "{inc.license}"')
        if inc.pose:
            parts.append(f'pose "{inc.pose}"')
        parts.append(f"from {inc.where}")
        lines.append(f"   {prefix}: " + ", ".join(parts))
    return etree.Comment(_comment_text("\n".join(lines) + "\n"))


def _section(item: _Item) -> int:
    tag = item.tag
    if tag == "_trailing":
        return _UNKNOWN_SECTION + 1
    return SECTIONS.index(tag) if tag in SECTIONS else _UNKNOWN_SECTION


def _serialize(root_doc: Document, expansion: _Expansion, frames: dict[str, str]) -> bytes:
    src = root_doc.root
    out = etree.Element(src.tag, nsmap=src.nsmap)  # type: ignore[arg-type]  # lxml-stubs: a None (default) prefix is allowed
    for key, value in src.attrib.items():
        out.set(key, value)
    for attr, value in frames.items():
        if out.get(attr) is None:
            out.set(attr, value)

    for item in expansion.items:
        if item.original is not None and item.name is not None:
            item.el.set("name", item.name)
        if item.pose is not None:
            pose = etree.Element("pose")
            pose.text = format_pose(item.pose)
            item.el.insert(0, pose)
    ordered = sorted(expansion.items, key=_section)  # stable: document order within a section
    merged: etree._Element | None = None
    placed: list[tuple[int, list[etree._Element]]] = []
    provenance_done = not expansion.included
    for item in ordered:
        section = _section(item)
        if not provenance_done and section >= len(METADATA):
            placed.append((len(METADATA), [_provenance(root_doc, expansion.included)]))
            provenance_done = True
        nodes = [*item.comments]
        if item.tag == "self-collision-disable":
            if merged is None:
                merged = item.el
                nodes.append(item.el)
            else:
                for c in nodes:
                    merged.append(c)
                for c in list(item.el):
                    merged.append(c)
                continue
        elif item.tag != "_trailing":
            nodes.append(item.el)
        placed.append((section, nodes))
    if not provenance_done:
        placed.append((len(METADATA), [_provenance(root_doc, expansion.included)]))

    boundaries: list[etree._Element] = []
    previous: int | None = None
    last: etree._Element | None = None
    for section, nodes in placed:
        if previous is not None and section != previous and last is not None:
            boundaries.append(last)
        for node in nodes:
            out.append(node)
            last = node
        previous = section
    _strip_whitespace(out)
    etree.indent(out, space="  ")
    for node in boundaries:  # a blank line between sections
        node.tail = "\n" + (node.tail or "")

    chunks = [b'<?xml version="1.0" encoding="UTF-8"?>']
    chunks += [_bytes(c) for c in _siblings(src, before=True)]
    chunks.append(_bytes(out))
    chunks += [_bytes(c) for c in _siblings(src, before=False)]
    return b"\n".join(chunks) + b"\n"


def _bytes(node: etree._Element) -> bytes:
    """``node`` serialised without its tail (no copy: the output tree may be large)."""
    tail, node.tail = node.tail, None
    try:
        return etree.tostring(node, encoding="UTF-8", xml_declaration=False).strip()
    finally:
        node.tail = tail


def _strip_whitespace(out: etree._Element) -> None:
    """Reset indentation whitespace so :func:`etree.indent` lays out every copy alike."""
    for el in out.iter():
        if el.text is not None and not el.text.strip() and len(el):
            el.text = None
        if el is not out and el.tail is not None and not el.tail.strip():
            el.tail = None


def _siblings(el: etree._Element, *, before: bool) -> Iterator[etree._Element]:
    """Comments before (or after) the root element, in document order."""
    found = []
    sib = el.getprevious() if before else el.getnext()
    while sib is not None:
        if isinstance(sib, etree._Comment):
            found.append(sib)
        sib = sib.getprevious() if before else sib.getnext()
    return iter(reversed(found) if before else found)
