"""Every file a model file names, checked before Drake opens any of them (a model file from someone else is
data: it may name any path).

Drake's parser opens what a URDF, SDF or MJCF file names: meshes (and an .obj's material
library, a material's textures, a glTF's buffers and images), textures, MJCF ``<include>``s,
SDF ``<include>``s. Meshcat then embeds a mesh's bytes in a replay page. So a model file from
someone else could copy ``/etc/passwd`` into a page that is sent on, or hang the process on
``/dev/random`` or a FIFO. :func:`scan_model` reads the model file (and the files it
includes) here first, with the standard library only:

- the XML has no DOCTYPE and no ENTITY declarations (no entity expansion at all);
- every named file resolves, symlinks followed, inside the model's folder or a declared
  package's folder (``package://drake/``), is a regular file (not a device, FIFO or folder)
  of at most :data:`~hybridctl.limits.MAX_MESH_BYTES`, and has an extension of its kind
  (a mesh, a texture, an included model); a file that does not exist is left to Drake, which
  reports it;
- includes nest at most :data:`~hybridctl.limits.MAX_INCLUDE_DEPTH` deep, a file including
  itself (directly or through others) is refused, and the expanded model has at most
  :data:`~hybridctl.limits.MAX_BODIES` bodies and :data:`~hybridctl.limits.MAX_MODEL_FILES`
  file references;
- every number of the file is finite, and masses given are > 0.

A refusal is one :class:`~hybridctl.systems.multibody.ModelError` line naming the model file,
the file that names the reference and the reference. No pydrake here: the caller passes the
declared packages' folders.
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping
from xml.etree import ElementTree
from xml.parsers import expat

import numpy as np

from ..limits import MAX_BODIES, MAX_INCLUDE_DEPTH, MAX_MESH_BYTES, MAX_MODEL_BYTES, MAX_MODEL_FILES
from .multibody import ModelError

MODEL_SUFFIXES = (".urdf", ".sdf", ".xml")
"""Model files we hand to Drake: URDF, SDF and MJCF (``.xml``). Drake's other formats (model
directives ``.dmd.yaml``, USD) name files in ways this scan does not read, so they are refused."""
MESH_SUFFIXES = (".obj", ".gltf", ".glb", ".dae", ".stl", ".vtk", ".ply")
"""Mesh files a model may name: what Drake's geometry reads (.obj, .vtk, .gltf) or meshcat draws
(.obj, .gltf, .dae), and .stl / .ply / .glb that URDFs commonly name (Drake warns and skips them)."""
TEXTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".ktx2")
"""Image files a material (URDF ``<texture>``, SDF ``<drake:diffuse_map>``, .mtl ``map_Kd``, glTF) may name."""
MESH_PART_SUFFIXES = (".mtl", ".bin", *TEXTURE_SUFFIXES)
"""Files a mesh itself names: an .obj's material library, a glTF's buffers, and textures."""

_TEXTURE_TAGS = ("texture", "diffuse_map", "albedo_map", "normal_map", "roughness_map", "metalness_map",
                 "emissive_map", "ambient_occlusion_map", "light_map")
_MTL_MAPS = ("bump", "disp", "decal", "refl", "norm")
_NUMBER = re.compile(r"[+-]?((\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|inf(inity)?|nan)$", re.IGNORECASE)
# attributes / elements that hold names or file references, never numbers
_NOT_NUMBERS = {"name", "type", "link", "joint", "parent", "child", "class", "childclass", "filename", "file",
                "uri", "meshdir", "texturedir", "assetdir", "model", "mesh", "texture", "material", "body"}


@dataclass
class ModelScan:
    """What :func:`scan_model` read: every file (the model's first), the expanded body count."""

    files: list[Path] = field(default_factory=list)
    bodies: int = 0
    references: int = 0


def scan_model(path: str | Path, packages: Mapping[str, str | Path] | None = None) -> ModelScan:
    """Check the model file ``path`` and every file it names (see the module docstring); ModelError if not."""
    top = Path(path)
    scanner = _Scanner(top, {name: Path(os.path.realpath(root)) for name, root in (packages or {}).items()})
    bodies, references = scanner.model(top, depth=0, stack=())
    return ModelScan(files=list(scanner.seen), bodies=bodies, references=references)


def regular_file(path: Path, limit: int, what: str) -> os.stat_result:
    """The stat of ``path`` (symlinks followed) if it is a regular file of at most ``limit`` bytes; ModelError
    naming ``what`` otherwise. Never opens the file, so a FIFO or a device cannot block here."""
    try:
        info = os.stat(path)
    except OSError as exc:
        raise ModelError(f"{what}: cannot be read ({exc.strerror})") from None
    if not stat.S_ISREG(info.st_mode):
        kind = ("a FIFO" if stat.S_ISFIFO(info.st_mode) else "a device" if stat.S_ISCHR(info.st_mode)
                or stat.S_ISBLK(info.st_mode) else "a folder" if stat.S_ISDIR(info.st_mode) else "a special file")
        raise ModelError(f"{what}: is {kind}, not a regular file; refused")
    if info.st_size > limit:
        raise ModelError(f"{what}: {info.st_size:,} bytes, above the limit of {limit:,}")
    return info


def read_bounded(path: Path, limit: int, what: str) -> bytes:
    """The bytes of regular file ``path``, at most ``limit`` (checked before and while reading)."""
    regular_file(path, limit, what)
    with open(path, "rb", buffering=0) as handle:   # O_NONBLOCK is moot: it is a regular file
        data = handle.read(limit + 1)
    if len(data) > limit:
        raise ModelError(f"{what}: grew above the limit of {limit:,} bytes while read")
    return data


def parse_xml(data: bytes, what: str) -> ElementTree.Element:
    """The XML ``data`` as an element tree; refused if it declares a DOCTYPE or an ENTITY (entity expansion
    is how an XML file grows a billion times on parsing, or reads a local file)."""
    def refuse(*_args):
        raise ModelError(f"{what}: declares a DOCTYPE or ENTITY; model files may not (entity expansion)")

    builder = ElementTree.TreeBuilder()
    parser = expat.ParserCreate()
    parser.StartDoctypeDeclHandler = refuse
    parser.EntityDeclHandler = refuse
    parser.ExternalEntityRefHandler = refuse
    parser.StartElementHandler = builder.start
    parser.EndElementHandler = builder.end
    parser.CharacterDataHandler = builder.data
    parser.buffer_text = True
    try:
        parser.Parse(data, True)
        root = builder.close()
    except expat.ExpatError as exc:
        raise ModelError(f"{what} does not parse: {expat.ErrorString(exc.code)} (XML line {exc.lineno})") from None
    except AssertionError:   # TreeBuilder with no root element
        root = None
    if root is None:
        raise ModelError(f"{what}: holds no XML element")
    return root


def _local(tag: str) -> str:
    return tag.rpartition(":")[2]


def _owner(element: ElementTree.Element, parents: dict) -> str:
    """' of body NAME' for the nearest enclosing link or body with a name ('' if none)."""
    while element is not None:
        if _local(element.tag) in ("link", "body") and element.get("name"):
            return f" of body {element.get('name')!r}"
        element = parents.get(element)
    return ""


class _Scanner:
    def __init__(self, top: Path, packages: dict[str, Path]):
        self.top = top
        self.folder = Path(os.path.realpath(top.parent))
        self.roots = [self.folder, *packages.values()]
        self.packages = packages
        self.seen: dict[Path, None] = {}
        # (bodies, file references) of each model file with its includes expanded, as Drake expands them
        self.counted: dict[Path, tuple[int, int]] = {}

    def fail(self, message: str):
        raise ModelError(f"model file {self.top}: {message}")

    def where(self, ref: str, named_in: Path) -> str:
        return f"{ref!r} (named in {named_in.name})" if named_in != self.top else repr(ref)

    # ------------------------------------------------------------------ references
    def resolve(self, ref: str, bases: list[Path], named_in: Path) -> list[Path]:
        """Every path ``ref`` may stand for, each inside a root (ModelError otherwise)."""
        ref = original = ref.strip()
        if ref.startswith("file://"):
            ref = ref[len("file://"):]
        scheme = re.match(r"([a-zA-Z][a-zA-Z0-9+.-]*)://(.*)$", ref)
        if scheme:
            kind, rest = scheme.groups()
            package, _, inner = rest.partition("/")
            if kind not in ("package", "model") or package not in self.packages:
                declared = ", ".join(f"package://{p}/" for p in self.packages) or "none"
                self.fail(f"names {self.where(original, named_in)}; only files in the model's folder or a declared "
                          f"package ({declared}) are read")
            candidates = [self.packages[package] / inner]
        elif "://" in ref or ref.startswith("data:"):
            self.fail(f"names {self.where(original, named_in)}, which is not a file path")
        else:
            path = Path(ref).expanduser()
            candidates = [path] if path.is_absolute() else [base / path for base in bases]
        resolved = []
        for candidate in candidates:
            real = Path(os.path.realpath(candidate))
            if not any(real == root or root in real.parents for root in self.roots):
                which = f", which is {real}" if str(real) != ref else ""
                self.fail(f"names {self.where(original, named_in)}{which}: outside the model's folder "
                          f"{self.folder}; refused (only files in it or in a declared package are read)")
            resolved.append(real)
        return resolved

    def reference(self, ref: str, bases: list[Path], named_in: Path, suffixes: tuple[str, ...], kind: str,
                  total: list[int], limit: int | None = None) -> list[Path]:
        """The existing files ``ref`` stands for, each checked: a regular file, of ``suffixes``, at most ``limit``
        (default :data:`~hybridctl.limits.MAX_MESH_BYTES`)."""
        limit = MAX_MESH_BYTES if limit is None else limit
        self.add(total, 0, 1)
        found = []
        for real in self.resolve(ref, bases, named_in):
            if not real.exists():
                continue   # Drake reports a missing file itself; nothing is read
            if real.suffix.lower() not in suffixes:
                self.fail(f"names {self.where(ref, named_in)} as a {kind}; a {kind} must be a "
                          f"{', '.join(suffixes)} file; refused")
            try:
                regular_file(real, limit, f"{kind} {real}")
            except ModelError as exc:
                self.fail(f"names {self.where(ref, named_in)}: {exc}")
            self.seen.setdefault(real)
            found.append(real)
        return found

    # ------------------------------------------------------------------ model files
    def model(self, path: Path, depth: int, stack: tuple[Path, ...]) -> tuple[int, int]:
        """Check model file ``path`` and what it names; its bodies and file references with includes expanded."""
        real = Path(os.path.realpath(path))
        if real in stack:
            self.fail(f"{real.name} includes itself (through {' -> '.join(p.name for p in (*stack, real))}); refused")
        if depth > MAX_INCLUDE_DEPTH:
            self.fail(f"includes nest deeper than {MAX_INCLUDE_DEPTH} (hybridctl.limits.MAX_INCLUDE_DEPTH)")
        if real in self.counted:
            return self.counted[real]
        if real.suffix.lower() not in MODEL_SUFFIXES:
            self.fail(f"{'includes ' + str(real) + ', which is' if stack else 'is'} not a URDF, SDF or MJCF "
                      f"file ({', '.join(MODEL_SUFFIXES)}); refused")
        try:
            data = read_bounded(real, MAX_MODEL_BYTES, f"model file {real}")
        except ModelError as exc:
            if not stack:
                raise
            self.fail(f"includes {exc}")
        self.seen.setdefault(real)
        root = parse_xml(data, f"model file {real}" if stack else f"model file {self.top}")
        total = [self.numbers(root, real), 0]   # bodies, references of this file with its includes expanded
        self.check_total(total)
        walk = self.mjcf if _local(root.tag) == "mujoco" else self.urdf_sdf
        walk(root, real, depth, (*stack, real), total)
        counts = self.counted[real] = (total[0], total[1])
        return counts

    def add(self, total: list[int], bodies: int, references: int) -> None:
        total[0] += bodies
        total[1] += references
        self.check_total(total)

    def check_total(self, total: list[int]) -> None:
        bodies, references = total
        if bodies > MAX_BODIES:
            self.fail(f"has more than {MAX_BODIES:,} bodies (links) with its includes expanded "
                      f"(hybridctl.limits.MAX_BODIES)")
        if references > MAX_MODEL_FILES:
            self.fail(f"names more than {MAX_MODEL_FILES:,} files with its includes expanded "
                      f"(hybridctl.limits.MAX_MODEL_FILES)")

    def numbers(self, root: ElementTree.Element, path: Path) -> int:
        """Refuse a non-finite number or a mass <= 0 anywhere in the file; the file's own body count."""
        bodies = 0
        parents = {child: parent for parent in root.iter() for child in parent}
        for element in root.iter():
            tag = _local(element.tag)
            bodies += tag in ("link", "body")
            values = [(key, value) for key, value in element.attrib.items()]
            if element.text and element.text.strip() and len(element) == 0:
                values.append((None, element.text))
            for key, value in values:
                if _local(key or tag) in _NOT_NUMBERS:
                    continue
                tokens = value.split()
                if not tokens or not all(_NUMBER.match(t) for t in tokens):
                    continue
                numbers = [float(t) for t in tokens]
                label = f"<{tag}{' ' + key if key else ''}>" + (f" of {element.get('name')!r}" if element.get("name") else "")
                if not all(math.isfinite(x) for x in numbers):
                    self.fail(f"{label} is {value.strip()!r} in {path.name}: every number of a model must be finite")
                is_mass = (tag == "mass" and key in (None, "value")) or (key == "mass" and tag == "inertial")
                if is_mass and numbers[0] <= 0:
                    self.fail(f"{label} is {value.strip()} kg in {path.name}: a mass must be > 0 "
                              f"(leave out <inertial> for a massless frame)")
            if tag in ("inertia", "inertial"):
                self.inertia(element, tag, path, _owner(element, parents))
        return bodies

    def inertia(self, element: ElementTree.Element, tag: str, path: Path, owner: str) -> None:
        """Refuse an inertia that is not positive semidefinite or breaks the triangle inequality (Drake warns
        and goes on). URDF ``<inertia ixx=...>``, SDF ``<inertia><ixx>..``, MJCF ``diaginertia`` / ``fullinertia``."""
        keys = ("ixx", "iyy", "izz", "ixy", "ixz", "iyz")
        given = {**element.attrib, **{_local(c.tag): (c.text or "") for c in element}}
        try:
            if tag == "inertia" and any(k in given for k in keys):
                ixx, iyy, izz, ixy, ixz, iyz = (float(given.get(k, 0.0)) for k in keys)
            elif tag == "inertial" and ("diaginertia" in given or "fullinertia" in given):
                values = [float(t) for t in given.get("fullinertia", given.get("diaginertia", "")).split()]
                ixx, iyy, izz, ixy, ixz, iyz = (values + [0.0] * 6)[:6]
            else:
                return
        except ValueError:
            return   # not numbers: Drake's parser names it
        matrix = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        if not np.isfinite(matrix).all():
            return   # refused as a non-finite number above
        moments = np.linalg.eigvalsh(matrix)
        tolerance = 1e-9 * max(1e-30, float(np.abs(moments).max()))
        shown = ", ".join(f"{m:g}" for m in moments)
        if moments.min() < -tolerance:
            self.fail(f"<{tag}>{owner} in {path.name} has principal moments {shown}: an inertia must be "
                      f"positive semidefinite")
        if moments.max() > moments.sum() - moments.max() + tolerance:
            self.fail(f"<{tag}>{owner} in {path.name} has principal moments {shown}, which break the triangle "
                      f"inequality (each at most the sum of the other two)")

    def include(self, ref: str, bases: list[Path], path: Path, depth: int, stack: tuple[Path, ...],
                total: list[int]) -> None:
        for included in self.reference(ref, bases, path, MODEL_SUFFIXES, "included model", total, MAX_MODEL_BYTES):
            self.add(total, *self.model(included, depth + 1, stack))

    def urdf_sdf(self, root: ElementTree.Element, path: Path, depth: int, stack: tuple[Path, ...],
                 total: list[int]) -> None:
        bases = [path.parent] if path.parent == self.folder else [path.parent, self.folder]
        for element in root.iter():
            tag = _local(element.tag)
            if tag == "include":   # SDF: <include><uri>a file</uri></include>
                for uri in [c.text for c in element if _local(c.tag) == "uri" and c.text and c.text.strip()]:
                    self.include(uri, bases, path, depth, stack, total)
            elif tag == "mesh":   # URDF <mesh filename>; SDF <mesh><uri>
                refs = [element.get("filename")] + [c.text for c in element if _local(c.tag) == "uri"]
                for ref in [r for r in refs if r and r.strip()]:
                    for mesh in self.reference(ref, bases, path, MESH_SUFFIXES, "mesh", total):
                        self.mesh_parts(mesh, total)
            elif tag in _TEXTURE_TAGS:
                for ref in [r for r in (element.get("filename"), element.text) if r and r.strip()]:
                    self.reference(ref, bases, path, TEXTURE_SUFFIXES, "texture", total)
            # any other <uri> (an SDF <plugin>'s) Drake does not open

    def mjcf(self, root: ElementTree.Element, path: Path, depth: int, stack: tuple[Path, ...],
             total: list[int]) -> None:
        dirs = {key: compiler.get(key) for compiler in root.iter("compiler")
                for key in ("meshdir", "texturedir", "assetdir") if compiler.get(key)}
        bases = [path.parent] if path.parent == self.folder else [path.parent, self.folder]

        def under(*keys):   # MuJoCo looks in meshdir / texturedir / assetdir; we check every reading
            found = list(bases)
            for key in [k for k in keys if k in dirs]:
                folder = Path(dirs[key]).expanduser()
                found += [folder] if folder.is_absolute() else [b / folder for b in bases]
            return found

        for element in root.iter():
            tag, ref = _local(element.tag), element.get("file")
            if not ref:
                continue
            if tag == "include":
                self.include(ref, bases, path, depth, stack, total)
            elif tag == "mesh":
                for mesh in self.reference(ref, under("meshdir", "assetdir"), path, MESH_SUFFIXES, "mesh", total):
                    self.mesh_parts(mesh, total)
            elif tag in ("texture", "hfield", "skin"):
                suffixes = TEXTURE_SUFFIXES if tag == "texture" else (".png", ".bin", ".skn")
                self.reference(ref, under("texturedir", "assetdir"), path, suffixes, tag, total)
            else:
                self.fail(f"<{tag} file={ref!r}> in {path.name}: a file reference Drake's MJCF parser does not "
                          f"read; refused")

    # ------------------------------------------------------------------ what a mesh names
    def mesh_parts(self, mesh: Path, total: list[int]) -> None:
        """An .obj's ``mtllib`` and a material's maps, a glTF's buffers and images: files meshcat embeds too."""
        suffix = mesh.suffix.lower()
        if suffix not in (".obj", ".gltf", ".glb"):
            return
        data = read_bounded(mesh, MAX_MESH_BYTES, f"mesh {mesh}")
        bases = [mesh.parent]
        if suffix == ".obj":
            for line in data.decode("utf-8", "replace").splitlines():
                words = line.split(None, 1)
                if len(words) == 2 and words[0] == "mtllib":
                    for library in self.reference(words[1].strip(), bases, mesh, (".mtl",), "material library",
                                                  total):
                        self.material(library, total)
            return
        try:
            if suffix == ".glb":
                if len(data) < 20 or data[:4] != b"glTF":
                    return   # not glTF: Drake refuses it itself
                length, = struct.unpack_from("<I", data, 12)
                data = data[20:20 + length]
            doc = json.loads(data)
        except (ValueError, struct.error):
            return   # not glTF: Drake refuses it itself
        for key, suffixes in (("buffers", (".bin",)), ("images", TEXTURE_SUFFIXES)):
            entries = doc.get(key, []) if isinstance(doc, dict) else []
            for entry in entries if isinstance(entries, list) else []:
                uri = entry.get("uri") if isinstance(entry, dict) else None
                if isinstance(uri, str) and not uri.startswith("data:"):
                    self.reference(uri, bases, mesh, suffixes, f"glTF {key[:-1]}", total)

    def material(self, library: Path, total: list[int]) -> None:
        text = read_bounded(library, MAX_MESH_BYTES, f"material library {library}").decode("utf-8", "replace")
        for words in (line.split() for line in text.splitlines()):
            if len(words) > 1 and (words[0].lower().startswith("map_") or words[0].lower() in _MTL_MAPS):
                self.reference(words[-1], [library.parent], library, TEXTURE_SUFFIXES, "texture", total)
