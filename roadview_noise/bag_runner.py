"""The bag pipeline: augment the mapped topics of a ROS bag, copy every other message unchanged, write one bag.

Messages are read in record order; those of mapped topics go to worker processes (:func:`ordered_map` on the file
runner's crash-safe executor, bounded in flight), and every message is written in record order with its record time.
A message whose augmentation fails, or whose worker dies (twice), is recorded in the manifest and copied unchanged,
never dropped.

Keys. A message is ``TOPIC@STAMP`` (header stamp in ns; ``#k`` for the k-th repeat of a stamp on its topic), which
``rvnoise replay`` takes. Every random draw is keyed by the message's **seed key**, the path ``rvnoise export`` gives
it (``camera/image/compressed/1700000000123456789.jpg``), and its sensor instance is the topic's folder
(``camera/image/compressed``): augmenting the exported tree with the same chains and seed draws the same values,
so files and bag carry the same pixels and points.
"""

from __future__ import annotations

import hashlib
import pickle
import struct
import sys
import time
import traceback
import warnings
from collections import deque
from contextlib import ExitStack, closing
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Container, Iterable, Iterator

from .bag_camera_info import CameraInfoIndex, CameraInfoWarnings, paired_topics
from .bag_recipe import BagRecipe, BagTopic, topic_folder
from .errors import EmptyCloudError, InputError, RecipeError, RvNoiseError
from .io import ros_messages as rm
from .io.atomic import atomic_path
from .io.rosbag import bag_kind, bag_output, header_stamp_ns, open_bag, output_kind, remove_stale_siblings
from .io.spool import Payload, Spool, load, put_beside
from .manifest import dumps, library_versions, read_manifest, write_run_json
from .resources import usable_cores
from .runner import RunSummary

DEPTH_WINDOW_NS = 1_000_000_000       # an aligned depth message is looked for within ±1 s of record time
MAX_IN_FLIGHT_BYTES = 256 << 20       # serialised messages held between reading and writing
TASKS_AHEAD_PER_WORKER = 4            # messages read ahead of the oldest unwritten one (a slow one stalls no worker)
MANIFEST_SUFFIX = ".manifest.jsonl"
RUN_SUFFIX = ".run.json"


def manifest_path(out_bag: Path) -> Path:
    """``OUT.bag.manifest.jsonl`` next to the output bag (file or ROS 2 folder)."""
    return out_bag.with_name(out_bag.name + MANIFEST_SUFFIX)


def run_record_path(out_bag: Path) -> Path:
    return out_bag.with_name(out_bag.name + RUN_SUFFIX)


def message_key(topic: str, stamp_ns: int, repeat: int) -> str:
    return f"{topic}@{stamp_ns}" + (f"#{repeat}" if repeat else "")


def export_stem(topic: str, stamp_ns: int, repeat: int) -> str:
    """Path of a message in an exported tree, without suffix: ``<topic folder>/<19-digit stamp>[_k]``."""
    return f"{topic_folder(topic)}/{stamp_ns:019d}" + (f"_{repeat}" if repeat else "")


def export_suffix(msg: Any, msgtype: str, source: str = "") -> str:
    """The file type a message is exported as: its own JPEG/PNG, ``.png`` for an Image, ``.raw`` for Bayer,
    ``.pcd`` for a cloud."""
    if msgtype == rm.COMPRESSED_IMAGE:
        return ".jpg" if rm.compressed_format(msg, source=source) == "jpeg" else ".png"
    if msgtype == rm.IMAGE:
        return ".raw" if rm.PIXEL_LAYOUTS.get(msg.encoding, rm.PIXEL_LAYOUTS["mono8"]).order == "bayer" else ".png"
    return ".pcd"


# --- the work of one message (in a worker) ----------------------------------------------------------------------------


@dataclass(frozen=True)
class MessageJob:
    topic: str
    msgtype: str
    stamp_ns: int
    repeat: int                      # earlier messages of the topic with the same stamp
    record_time_ns: int
    raw: bytes                       # (a spool.Spooled on its way to a worker)
    depth: tuple[str, bytes] | None  # (msgtype, raw) of the aligned depth message (raw spooled, like ``raw``)
    camera_info: tuple[str, int, bytes, bool] | None = None   # CameraInfoIndex.at: (topic, stamp, raw, after)

    @property
    def key(self) -> str:
        return message_key(self.topic, self.stamp_ns, self.repeat)


@dataclass(frozen=True)
class BagContext:
    """What a worker needs besides the message: the recipe, the bag's message types, where relative profile files
    are looked for."""

    bag: str
    is2: bool
    fielddefs: dict
    recipe: BagRecipe
    bag_dir: Path
    capture_output: bool = False         # what native libraries print goes to the entry (runner.RunContext)


@lru_cache(maxsize=4)
def _context(blob: bytes) -> tuple[BagContext, Any]:
    from rosbags.typesys import Stores, get_typestore

    ctx = pickle.loads(blob)
    typestore = get_typestore(Stores.EMPTY)
    typestore.register(ctx.fielddefs)
    return ctx, typestore


def augment_message(blob: bytes, job: MessageJob) -> tuple[dict[str, Any], bytes | None]:
    """Run the topic's chain on one message: (manifest entry, serialised output or None when it failed). The entry
    carries what a file's entry does where it applies (input notes, dropped invalid points, step and output metrics,
    warnings, what native libraries printed)."""
    import cv2

    from .allocator import keep_freed_memory
    from .native_output import captured_output

    cv2.setNumThreads(1)
    keep_freed_memory()
    t0 = time.perf_counter()
    ctx, typestore = _context(blob)
    topic = ctx.recipe.topics[job.topic]
    entry: dict[str, Any] = {
        "key": job.key, "topic": job.topic, "stamp_ns": job.stamp_ns, "record_time_ns": job.record_time_ns,
        "msgtype": job.msgtype, "sequence": topic.sequence_id, "chain": list(topic.recipe.model_ids),
        "input_sha256": hashlib.sha256(job.raw).hexdigest(),
    }
    with captured_output(ctx.capture_output) as printed:
        out = _augment(ctx, typestore, topic, job, entry)
    if printed:
        entry["library_messages"] = printed
    entry["seconds"] = round(time.perf_counter() - t0, 4)
    return entry, out


def _augment(ctx: BagContext, typestore: Any, topic: BagTopic, job: MessageJob, entry: dict[str, Any]
             ) -> bytes | None:
    """The body of :func:`augment_message`: fills ``entry``, returns the serialised output (None: failed)."""
    from .compound import apply_models
    from .dataset import Sample
    from .invalid_points import drop_invalid_points
    from .metrics import compare
    from .runner import Task, _warning_list, build_models

    source = f"{ctx.bag}: {job.key}"
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            msg = _deserialize(typestore, ctx.is2, job.raw, job.msgtype, source)
            seed_key = export_stem(job.topic, job.stamp_ns, job.repeat) + export_suffix(msg, job.msgtype, source)
            entry["seed_key"] = seed_key
            try:
                data = message_data(ctx, typestore, topic, msg, job, source)
            except EmptyCloudError as e:       # a radar frame without detections: nothing to augment, as for files
                entry.pop("seed_key")
                entry.update(status="ok", copied_unchanged=True, note=str(e).removeprefix(f"{source}: "),
                             metrics={}, steps=[], output_sha256=entry["input_sha256"])
                return None
            if getattr(data, "input_notes", None):
                entry["inputs"] = dict(data.input_notes)
            data, dropped = drop_invalid_points(data, file=source)
            if dropped:
                entry["input_warnings"] = dropped
            recipe = topic.recipe
            metrics = recipe.spec.output.metrics
            models = build_models(recipe, Task(Sample(seed_key, topic.sensor, topic.sequence_id), 0, seed_key))
            result, records = apply_models(models, data, seed=recipe.seed, key=seed_key,
                                           sequence_id=topic.sequence_id, metrics=metrics)
            entry["steps"] = [r.as_entry() for r in records]
            entry["metrics"] = compare(data, result) if metrics else {}
            new = (rm.frame_to_image(msg, job.msgtype, result, source=source) if topic.sensor == "camera" else
                   rm.pointcloud_to_cloud2(msg, result, effect=recipe.spec.output.effect, source=source))
            out = _serialize(typestore, ctx.is2, new, job.msgtype, job.raw)
        if caught:
            entry["warnings"] = _warning_list(caught)
        entry.update(output_sha256=hashlib.sha256(out).hexdigest(), status="ok")
        return out
    except RvNoiseError as e:
        entry.update(status="failed", error=str(e) if source in str(e) else f"{source}: {e}", copied_unchanged=True)
    except Exception as e:  # a bug or library error on one message must not stop the run; keep the trace
        entry.update(status="failed", error=f"{source}: internal error {type(e).__name__}: {e}",
                     traceback=traceback.format_exc(limit=8), copied_unchanged=True)
    return None


def message_data(ctx: BagContext, typestore: Any, topic: BagTopic, msg: Any, job: MessageJob, source: str):
    """The frame (with the geometry and depth its chain needs, :func:`camera_inputs.with_camera_inputs`) or cloud
    of a message, with its topic's profile and conditions."""
    from .camera_inputs import with_camera_inputs
    from .dataset import with_conditions

    data = sensor_data(ctx, topic, msg, job.msgtype, source)
    if topic.sensor == "camera":
        data = with_camera_inputs(data, topic.recipe, TopicImage(ctx, typestore, topic, job, source))
    return with_conditions(data, topic.recipe)


def sensor_data(ctx: BagContext, topic: BagTopic, msg: Any, msgtype: str, source: str):
    """A message as a frame (pixels and encoding; no profile yet) or a cloud with its topic's profile."""
    from .dataset import cloud_profile_for

    recipe, spec = topic.recipe, topic.spec
    inputs = recipe.spec.inputs
    if topic.sensor != "camera":
        profile = cloud_profile_for(topic.sensor, inputs, ctx.bag_dir, recipe, sidecar=False)
        return rm.cloud_to_pointcloud(msg, sensor=topic.sensor, profile=profile,
                                      field_map=dict(inputs.field_map) or None, source=source)
    return rm.image_to_frame(msg, msgtype, None, source=source, black_level_dn=spec.black_level_dn,
                             white_level_dn=spec.white_level_dn,
                             untagged_transfer=inputs.untagged_transfer or "srgb")


class TopicImage:
    """A camera topic's message as the origin of a frame (:func:`camera_inputs.with_camera_inputs`): profile paths
    next to the recipe, then the bag (no ``camera.yaml`` lookup); its aligned depth message is the ``file`` depth
    source."""

    sidecars = False

    def __init__(self, ctx: BagContext, typestore: Any, topic: BagTopic, job: MessageJob, source: str):
        self.ctx, self.typestore, self.topic, self.job = ctx, typestore, topic, job
        self.name, self.folder = source, ctx.bag_dir

    def key(self, setting: str) -> str:
        return f"topics.{self.topic.name}.{setting}"

    def stated_intrinsics(self, width_px: int, height_px: int):
        """The intrinsics of the image's CameraInfo (:mod:`roadview_noise.bag_camera_info`), None without one."""
        from .bag_camera_info import stated_intrinsics

        info = self.job.camera_info
        if info is None:
            return None
        where = f"{info[0]}@{info[1]}"                        # errors read "<bag>: <camera key>: <where>: …"
        msg = _deserialize(self.typestore, self.ctx.is2, info[2], rm.CAMERA_INFO, where)
        return stated_intrinsics(msg, info, self.topic.name, self.topic.spec.camera_info_matrix, width_px,
                                 height_px, source=where)

    def depth(self, recipe, geometry) -> tuple[Any, dict, str]:
        """Range along each pixel ray (m; NaN holes, ``inf`` too far) of the aligned depth message: planar z
        (REP 118) unless the topic's ``depth_kind`` is ``range``."""
        import numpy as np

        from .units import planar_depth_to_range

        depth_topic = self.topic.spec.depth_topic
        if self.job.depth is None:
            raise InputError(f"no message with stamp {self.job.stamp_ns} on depth topic {depth_topic}",
                             file=self.name)
        depth_type, depth_raw = self.job.depth
        where = f"{depth_topic}@{self.job.stamp_ns}"              # errors read "<bag>: <camera key>: <where>: …"
        msg = _deserialize(self.typestore, self.ctx.is2, depth_raw, depth_type, where)
        z = rm.depth_image_m(msg, depth_type, source=where)
        w, h = geometry.size
        if z.shape != (h, w):
            raise InputError(f"depth image is {z.shape[0]}×{z.shape[1]} (H×W) but the camera image is {h}×{w}",
                             file=where)
        kind = recipe.spec.inputs.depth_kind
        if kind == "planar":
            p = geometry.profile
            z = planar_depth_to_range(z, p.fx_px, p.fy_px, p.cx_px, p.cy_px)
        notes = {"source": "topic", "topic": depth_topic, "kind": kind,
                 "encoding": msg.format if depth_type == rm.COMPRESSED_IMAGE else msg.encoding}
        return np.ascontiguousarray(z, dtype=np.float32), notes, where


def _deserialize(typestore: Any, is2: bool, raw: bytes, msgtype: str, source: str) -> Any:
    from rosbags.serde import SerdeError

    try:
        return typestore.deserialize_cdr(raw, msgtype) if is2 else typestore.deserialize_ros1(raw, msgtype)
    except (SerdeError, ValueError, IndexError) as e:
        raise InputError(f"cannot deserialise the {msgtype} message: {e}", file=source) from None


def _serialize(typestore: Any, is2: bool, msg: Any, msgtype: str, like: bytes) -> bytes:
    """Serialised like the input message (CDR in the input's byte order)."""
    if is2:
        return bytes(typestore.serialize_cdr(msg, msgtype, little_endian=bool(like[1])))
    return bytes(typestore.serialize_ros1(msg, msgtype))


# --- parallel, in order, bounded --------------------------------------------------------------------------------------


def _augment_task(task: tuple[int, MessageJob], blob: bytes) -> tuple[dict[str, Any], Payload | None]:
    """The executor's task function: ``task`` = (sequence number, job with its message spooled or inline), the
    context is the pickled BagContext; the output comes back the way the message came (:mod:`io.spool`)."""
    job = task[1]
    depth = None if job.depth is None else (job.depth[0], load(job.depth[1]))
    entry, out = augment_message(blob, replace(job, raw=load(job.raw), depth=depth))
    return entry, None if out is None else put_beside(job.raw, out, ".out")


def ordered_map(fn: Callable, context: Any, items: Iterable[tuple[Any, Any, int]], workers: int, *,
                max_bytes: int = MAX_IN_FLIGHT_BYTES) -> Iterator[tuple[Any, Any]]:
    """Yield ``(item, result)`` in the order of ``items`` = ``(item, task or None, size in bytes)``: ``result`` is
    ``fn((k, task), context)`` (``None`` for an item without task), or the :class:`executor.WorkerDeath` /
    :class:`executor.TaskError` of a task whose worker died or that raised. Tasks run on the file runner's crash-safe
    :class:`executor.ProcessExecutor` (``workers`` processes, also for one: a dying worker costs its message, not the
    run; the run's plugin models adopted). At most ``TASKS_AHEAD_PER_WORKER``·``workers`` tasks and ``max_bytes`` of
    items are held between reading and yielding (the source answers :data:`executor.NOT_NOW` while over), so memory
    stays bounded on long bags while the workers stay busy."""
    from .executor import NOT_NOW, ProcessExecutor
    from .registry import adopt, plugin_models

    pending: deque[list] = deque()          # [item, result, done, size, is task] in the order of items
    ready: deque[list] = deque()            # done at the head of the order, to be yielded
    slots: dict[int, list] = {}
    held = tasks = 0

    def advance() -> None:
        while pending and pending[0][2]:
            ready.append(pending.popleft())

    def source() -> Iterator:
        nonlocal held, tasks
        for k, (item, task, size) in enumerate(items):
            while ready or (pending and (held > max_bytes or tasks >= TASKS_AHEAD_PER_WORKER * workers)):
                yield NOT_NOW                   # the head is running (or waits to be yielded): let results in
            slot = [item, None, task is None, size, task is not None]
            pending.append(slot)
            held += size
            if task is None:
                advance()
                continue
            slots[k] = slot
            tasks += 1
            yield k, task

    executor = ProcessExecutor(fn, context, max(1, workers), setup=(adopt, (plugin_models(),)))
    try:
        for task, result in executor.map(source()):
            if task is not NOT_NOW:
                slot = slots.pop(task[0])
                slot[1], slot[2] = result, True
                advance()
            while ready:
                item, result, _, size, is_task = ready.popleft()
                held -= size
                tasks -= is_task
                yield item, result
        advance()
        for item, result, *_ in ready:
            yield item, result
    finally:
        executor.close()


# --- planning and the run -------------------------------------------------------------------------------------------


@dataclass
class BagPlan:
    """The bag's connections by role: mapped topic connections, depth topic connections per depth topic; the
    CameraInfo messages of the camera topics that take their intrinsics from one."""

    mapped: dict[int, BagTopic]           # id(connection) → topic
    depth: dict[str, list]                # depth topic → its connections
    camera_info: CameraInfoIndex


def plan_bag(recipe: BagRecipe, reader: Any, bag: Path, *, every_camera: bool = False) -> BagPlan:
    """Check the recipe against the bag before anything is written: every mapped and depth topic exists and carries
    a message type its sensor reads (RecipeError names the bag, the topic and the type); read the CameraInfo
    messages of the camera topics that take their intrinsics from one (every camera topic without a stated profile
    with ``every_camera``, for export)."""
    from .registry import suggest

    by_topic: dict[str, list] = {}
    for conn in reader.connections:
        by_topic.setdefault(conn.topic, []).append(conn)
    mapped, depth = {}, {}
    for name, topic in recipe.topics.items():
        if name not in by_topic:
            raise RecipeError(f"topic {name!r} of the recipe is not in {str(bag)!r}{suggest(name, by_topic)} "
                              f"(its topics: {', '.join(sorted(by_topic))})", file=recipe.source, key=f"topics.{name}")
        for conn in by_topic[name]:
            allowed = rm.SENSOR_TYPES[topic.sensor]
            if conn.msgtype not in allowed:
                raise RecipeError(f"{bag}: topic {name} carries {conn.msgtype}, which a {topic.sensor} topic cannot "
                                  f"read (expected {' or '.join(allowed)}){rm.type_hint(conn.msgtype)}",
                                  file=recipe.source, key=f"topics.{name}")
            mapped[id(conn)] = topic
        want = topic.spec.depth_topic
        if want is not None:
            if want not in by_topic:
                raise RecipeError(f"depth topic {want!r} is not in {str(bag)!r}{suggest(want, by_topic)}",
                                  file=recipe.source, key=f"topics.{name}.depth_topic")
            bad = [c.msgtype for c in by_topic[want] if c.msgtype not in (rm.IMAGE, rm.COMPRESSED_IMAGE)]
            if bad:
                raise RecipeError(f"{bag}: depth topic {want} carries {bad[0]}, not {rm.IMAGE} (or a "
                                  f"compressedDepth {rm.COMPRESSED_IMAGE})", file=recipe.source,
                                  key=f"topics.{name}.depth_topic")
            depth[want] = by_topic[want]
    check_profiles(recipe, bag)
    pairs = paired_topics(recipe, by_topic, bag, every_camera=every_camera)
    return BagPlan(mapped, depth, CameraInfoIndex.read(reader, pairs, bag_kind(bag) == "ros2", bag))


def check_profiles(recipe: BagRecipe, bag: Path) -> None:
    """Load every topic's profile now, as a file run's ``validate`` does (a camera profile only when a step uses
    the camera geometry): a bad profile is a RecipeError naming the topic's key, not a failure of every message."""
    from .camera_inputs import needs_camera_geometry
    from .dataset import _camera_profile, _profile_spec, cloud_profile_for

    bag_dir = bag.resolve().parent
    for name, topic in recipe.topics.items():
        inputs = topic.recipe.spec.inputs
        try:
            if topic.sensor != "camera":
                cloud_profile_for(topic.sensor, inputs, bag_dir, topic.recipe, sidecar=False)
            elif inputs.camera_profile is not None and needs_camera_geometry(topic.recipe):
                _camera_profile(_profile_spec(inputs.camera_profile, bag_dir, topic.recipe), bag_dir)
        except InputError as e:
            raise RecipeError(f"invalid {topic.sensor} profile: {e}", file=recipe.source,
                              key=f"topics.{name}.{topic.sensor}_profile") from None


class DepthSync:
    """Depth messages of one topic by header stamp, read ahead on a second reader until the stamp asked for is found
    or ``DEPTH_WINDOW_NS`` past its record time, and kept until they are that much older (memory stays bounded)."""

    def __init__(self, messages: Iterator, is2: bool):
        self.messages, self.is2 = messages, is2
        self.buffer: dict[int, tuple[int, str, bytes]] = {}
        self.read_to = -2 ** 63

    def take(self, stamp_ns: int, record_time_ns: int) -> tuple[str, bytes] | None:
        while stamp_ns not in self.buffer and self.read_to <= record_time_ns + DEPTH_WINDOW_NS:
            nxt = next(self.messages, None)
            if nxt is None:
                self.read_to = 2 ** 63
                break
            conn, t, raw = nxt
            self.read_to = t
            self.buffer.setdefault(header_stamp_ns(raw, self.is2), (t, conn.msgtype, raw))
        for s in [s for s, (t, _, _) in self.buffer.items() if t < record_time_ns - DEPTH_WINDOW_NS]:
            del self.buffer[s]
        hit = self.buffer.get(stamp_ns)
        return None if hit is None else hit[1:]


def depth_syncs(stack: ExitStack, bag: Path, plan: BagPlan, is2: bool) -> dict[str, DepthSync]:
    """A :class:`DepthSync` per depth topic, reading ahead on a second reader of the bag (opened only if needed)."""
    if not plan.depth:
        return {}
    reader = stack.enter_context(open_bag(bag))
    return {t: DepthSync(reader.messages(connections=conns), is2) for t, conns in plan.depth.items()}


def check_bag_paths(in_bag: Path, out_bag: Path, overwrite: bool) -> None:
    """Refuse a missing input, an output that is the input or inside it, a family change (ROS 1 ↔ ROS 2), and an
    existing output without ``overwrite``."""
    kind = bag_kind(in_bag)
    if not in_bag.exists() or kind is None:
        raise RecipeError(f"input {str(in_bag)!r} is not a ROS bag (.bag, .mcap, .db3, or a ROS 2 bag folder)")
    a, b = in_bag.resolve(), out_bag.resolve()
    if a == b or a in b.parents:
        raise RecipeError(f"output {str(out_bag)!r} would overwrite or sit inside the input bag {str(in_bag)!r}")
    if output_kind(out_bag) != kind:
        want = ".bag" if kind == "ros1" else "a folder, .mcap or .db3"
        raise RecipeError(f"{str(in_bag)!r} is a {kind.upper()} bag; write it as {want} "
                          "(no ROS 1 ↔ ROS 2 conversion)")
    if out_bag.is_dir() and bag_kind(out_bag) is None and any(out_bag.iterdir()):
        raise RecipeError(f"{str(out_bag)!r} is a folder that is not a ROS 2 bag; name the output bag itself "
                          "(e.g. out/drive-rain.bag or out/drive-rain/ for ROS 2)")
    if (out_bag.exists() or manifest_path(out_bag).exists()) and not overwrite:
        raise RecipeError(f"{str(out_bag)!r} exists; use --overwrite to replace it")


def run_bag(recipe: BagRecipe, in_bag: Path, out_bag: Path, *, workers: int | None = None, overwrite: bool = False,
            progress: bool = True, max_in_flight_bytes: int = MAX_IN_FLIGHT_BYTES,
            echo: Callable[[str], None] = print) -> RunSummary:
    """Augment a bag; manifest ``OUT.manifest.jsonl`` and ``OUT.run.json`` next to it; input warnings (intrinsics
    assumed, depth holes filled …) once per run through ``echo``. Raises RecipeError/InputError (exit 2) when it
    cannot start or the bag cannot be read to its end; nothing is left half-written then."""
    from tqdm import tqdm

    from .allocator import keep_freed_memory
    from .runner import _Tally

    started = time.time()
    keep_freed_memory()                 # the serial reading and writing here reuse their buffers' pages
    in_bag, out_bag = Path(in_bag), Path(out_bag)
    check_bag_paths(in_bag, out_bag, overwrite)
    n_workers = workers or usable_cores()
    summary = RunSummary()
    tally = _Tally(summary)                    # counts, failures and warning lines, as a file run folds them
    topics: dict[str, dict[str, int]] = {t: {"messages": 0, "ok": 0, "failed": 0} for t in recipe.topics}
    for p in (out_bag, manifest_path(out_bag)):
        remove_stale_siblings(p)
    with ExitStack() as stack:
        reader = stack.enter_context(open_bag(in_bag))
        plan = plan_bag(recipe, reader, in_bag)
        is2 = bag_kind(in_bag) == "ros2"
        blob = pickle.dumps(BagContext(str(in_bag), is2, dict(reader.typestore.fielddefs), recipe,
                                       in_bag.resolve().parent, capture_output=True))
        syncs = depth_syncs(stack, in_bag, plan, is2)
        unpaired = sorted({c.topic for c in reader.connections if c.msgtype == rm.CAMERA_INFO} -
                          set(plan.camera_info.topic_of.values()))
        info_warnings = CameraInfoWarnings(unpaired)
        n_messages = reader.message_count
        bar = tqdm(total=n_messages, unit="msg", disable=not progress, file=sys.stderr, dynamic_ncols=True)
        try:
            with atomic_path(manifest_path(out_bag)) as manifest_tmp, \
                    open(manifest_tmp, "w", encoding="utf-8") as log, bag_output(out_bag, reader) as out:
                spool = stack.enter_context(closing(Spool()))
                jobs = spooled(message_jobs(reader, plan, syncs, is2, in_bag), spool)
                done = ordered_map(_augment_task, blob, jobs, n_workers, max_bytes=max_in_flight_bytes)
                for (conn, t, raw, job, sent), result in done:
                    bar.update(1)
                    if job is None:
                        out.write(conn, t, raw)
                        continue
                    spool.discard(sent.raw, *sent.depth[1:2] if sent.depth else ())
                    entry, data = result if isinstance(result, tuple) else (_lost_entry(job, result, in_bag), None)
                    data = None if data is None else spool.take(data)
                    out.write(conn, t, raw if data is None else data)
                    log.write(dumps(entry) + "\n")
                    empty = _is_empty_copy(entry)
                    tally.add({**entry, "skipped": True} if empty else entry)     # counted apart from augmented
                    info_warnings.add(entry)
                    summary.planned += 1
                    counts = topics[entry["topic"]]
                    counts["messages"] += 1
                    status = "empty" if empty else entry["status"] if entry["status"] == "ok" else "failed"
                    counts[status] = counts.get(status, 0) + 1
        finally:
            bar.close()
    summary.seconds = time.time() - started
    summary.warnings = tally.warnings() + info_warnings.lines()
    for line in summary.warnings:
        echo(f"rvnoise: warning: {line}")
    write_run_json(run_record_path(out_bag), {
        "tool": "rvnoise", "versions": {**library_versions(), "rosbags": _rosbags_version()},
        "recipe_source": recipe.source, "recipe_base_dir": str(recipe.base_dir), "recipe": recipe.resolved_dict(),
        "recipe_sha256": recipe.sha256(), "seed": recipe.seed, "input_bag": str(in_bag.resolve()),
        "output_bag": str(out_bag.resolve()), "workers": n_workers, "started_unix": started,
        "wall_seconds": round(summary.seconds, 3), "warnings": summary.warnings, "topics": topics,
        "counts": {"augmented": summary.done, "failed": summary.failed, "messages": n_messages,
                   **({"empty": summary.skipped} if summary.skipped else {})},
    })
    return summary


def _is_empty_copy(entry: dict[str, Any]) -> bool:
    """Whether a message's entry is a cloud with nothing to augment, copied unchanged (``status: ok`` with
    ``copied_unchanged``, as a file run records an empty cloud file; a failed message is copied unchanged too)."""
    return entry.get("status") == "ok" and bool(entry.get("copied_unchanged"))


def _lost_entry(job: MessageJob, result: Any, bag: Path) -> dict[str, Any]:
    """The manifest entry of a message whose worker died (as a file run records it, :func:`runner._result_entry`)
    or whose task raised past :func:`augment_message`: failed, copied unchanged."""
    from .executor import WorkerDeath

    entry: dict[str, Any] = {
        "key": job.key, "topic": job.topic, "stamp_ns": job.stamp_ns, "record_time_ns": job.record_time_ns,
        "msgtype": job.msgtype, "input_sha256": hashlib.sha256(job.raw).hexdigest(), "status": "failed",
        "copied_unchanged": True}
    if isinstance(result, WorkerDeath):
        again = " (tried twice, not retried again)" if result.deaths > 1 else ""
        entry.update(error=f"{bag}: {job.key}: {result.reason}{again}", worker_deaths=result.deaths)
    else:
        entry.update(error=f"{bag}: {job.key}: internal error {result.message}", traceback=result.traceback)
    return entry


def message_jobs(reader: Any, plan: BagPlan, syncs: dict[str, DepthSync], is2: bool, bag: Path
                 ) -> Iterator[tuple[tuple[Any, int, bytes, MessageJob | None], MessageJob | None, int]]:
    """Every message in record order as ``((connection, record time, raw, job), job or None, bytes held)``."""
    for conn, t, raw, stamp, repeat in stamped_messages(reader, plan.mapped, is2, bag):
        topic = plan.mapped.get(id(conn))
        if topic is None:
            yield (conn, t, raw, None), None, len(raw)
            continue
        depth = syncs[topic.spec.depth_topic].take(stamp, t) if topic.spec.depth_topic else None
        info = plan.camera_info.at(conn.topic, stamp)
        job = MessageJob(conn.topic, conn.msgtype, stamp, repeat, t, raw, depth, info)
        yield (conn, t, raw, job), job, len(raw) + (len(depth[1]) if depth else 0)


def spooled(jobs: Iterator[tuple[tuple, MessageJob | None, int]], spool: Spool) -> Iterator[tuple[tuple, Any, int]]:
    """:func:`message_jobs` with each job's message and depth message put in ``spool`` on their way to a worker;
    the job as sent is appended to the item (its spool files are discarded when the result is in)."""
    for item, job, size in jobs:
        sent = None
        if job is not None:
            depth = None if job.depth is None else (job.depth[0], spool.put(job.depth[1]))
            sent = replace(job, raw=spool.put(job.raw), depth=depth)
        yield (*item, sent), sent, size


def stamped_messages(reader: Any, mapped: Container[int], is2: bool, bag: Path, connections: list | None = None
                     ) -> Iterator[tuple[Any, int, bytes, int | None, int]]:
    """``(connection, record time, raw, header stamp, repeat)`` in record order (of ``connections`` or all); the stamp
    and its repeat count on the topic only for connections whose id is in ``mapped``. A read error mid-bag is an
    InputError naming the bag and the last message read."""
    repeats: dict[str, dict[int, int]] = {}
    last = "its first message"
    messages = reader.messages(connections=connections or ())
    while True:
        try:
            item = next(messages, None)
        except Exception as e:  # rosbags raises several types for a damaged chunk, record or database page
            raise InputError(f"cannot read the bag after {last} ({type(e).__name__}: {e})", file=str(bag)) from None
        if item is None:
            return
        conn, t, raw = item
        if id(conn) not in mapped:
            last = f"{conn.topic} at record time {t}"
            yield conn, t, raw, None, 0
            continue
        try:
            stamp = header_stamp_ns(raw, is2)
        except (struct.error, IndexError):
            raise InputError(f"{conn.topic} at record time {t}: the message is too short for a header",
                             file=str(bag)) from None
        seen = repeats.setdefault(conn.topic, {})
        repeat = seen.get(stamp, 0)
        seen[stamp] = repeat + 1
        last = message_key(conn.topic, stamp, repeat)
        yield conn, t, raw, stamp, repeat


def _rosbags_version() -> str:
    from importlib.metadata import version

    return version("rosbags")


def replay_bag(manifest: Path, key: str, *, out_file: Path | None = None, input_bag: Path | None = None
               ) -> dict[str, Any]:
    """Re-run the recorded chain on one message (``TOPIC@STAMP``) and compare the sha256 of its serialised output with
    the manifest's; the same result dict as :func:`runner.replay`."""
    import json

    from .bag_recipe import parse_bag_recipe
    from .registry import suggest

    manifest = Path(manifest)
    record_path = manifest.with_name(manifest.name[: -len(MANIFEST_SUFFIX)] + RUN_SUFFIX)
    if not record_path.is_file():
        raise RecipeError(f"no {record_path.name} next to {str(manifest)!r}; replay needs the run record")
    record = json.loads(record_path.read_text())
    entries = read_manifest(manifest)
    matching = [e for e in entries if e.get("key") == key]
    if not matching:
        raise RecipeError(f"no message {key!r} in {str(manifest)!r}{suggest(key, [e.get('key') for e in entries])}")
    entry = matching[-1]
    recipe = parse_bag_recipe(record["recipe"], source=str(record_path), base_dir=Path(record["recipe_base_dir"]))
    bag = Path(input_bag or record["input_bag"])
    with open_bag(bag) as reader:
        plan = plan_bag(recipe, reader, bag)
        is2 = bag_kind(bag) == "ros2"
        job = find_job(reader, plan, is2, bag, key)
        blob = pickle.dumps(BagContext(str(bag), is2, dict(reader.typestore.fielddefs), recipe, bag.resolve().parent))
    new, data = augment_message(blob, job)
    if data is not None and out_file is not None:
        Path(out_file).parent.mkdir(parents=True, exist_ok=True)
        Path(out_file).write_bytes(data)
    return {"key": key, "expected": entry.get("output_sha256"), "got": new.get("output_sha256"),
            "match": new.get("output_sha256") is not None and new.get("output_sha256") == entry.get("output_sha256"),
            "input_changed": new.get("input_sha256") != entry.get("input_sha256"), "error": new.get("error"),
            "output": str(out_file) if out_file else None,
            "files": [{"path": key, "expected": entry.get("output_sha256"), "got": new.get("output_sha256")}]}


def find_job(reader: Any, plan: BagPlan, is2: bool, bag: Path, key: str) -> MessageJob:
    """The job of message ``key`` with its aligned depth message (InputError when the bag no longer has it)."""
    topic_name = key.rsplit("@", 1)[0]
    conns = [c for c in reader.connections if id(c) in plan.mapped and c.topic == topic_name]
    for conn, t, raw, stamp, repeat in stamped_messages(reader, plan.mapped, is2, bag, connections=conns):
        if message_key(conn.topic, stamp, repeat) == key:
            topic = plan.mapped[id(conn)]
            depth = None
            if topic.spec.depth_topic:
                depth = DepthSync(reader.messages(connections=plan.depth[topic.spec.depth_topic]), is2).take(stamp, t)
            return MessageJob(conn.topic, conn.msgtype, stamp, repeat, t, raw, depth,
                              plan.camera_info.at(conn.topic, stamp))
    raise InputError(f"no message {key} in the bag", file=str(bag))
