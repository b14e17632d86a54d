"""One GRAND-SLAM agent split over two threads: tracking on the caller's thread, mapping and loop closure on a
worker thread beside it.

`RealtimeAgent.track` tracks a frame against the map mapping finished last and returns its pose without waiting
for the map. Then `hand_over_keyframe`, after the pose went out: when the frame is due to be a keyframe and the
worker is idle, it starts a submap if needed, adds the keyframe and hands it over; when the worker is still busy,
the keyframe is deferred (the next frame is asked again) and the worker is told to finish: it gives each keyframe
`runtime.min_mapping_iterations` at least and otherwise stops as soon as the next keyframe waits (at most
mapping.iterations, or runtime.max_mapping_iterations). `step` does both. The worker fits the keyframe's exposure
against the map first (renders of one or more submaps, kept off the tracker's time). After mapping, the worker renders the
tracker's model view of the new map (slam.dense.tracking.tracker build_view) and publishes both; the tracker takes
them up at its next frame. Loop closure runs after that, on the worker.

The threads share the map without locks by construction: the worker only changes the submap it maps (the tracker
reads the Gaussians published before), and the tracker changes the submaps and the keyframe list only while the
worker is idle (the worker packs a retired submap's keyframe images and moves its Gaussians to the map's store, as
its next job's first step).
Warp's kernels and torch's operators release the GIL, so the two threads run at the same time (the run measures
it: metrics.json realtime.cpu_s). The worker lowers its own priority (runtime.mapping_nice), so when the cores are
short the tracker runs first and mapping takes what is left.
"""

from __future__ import annotations

import os
import sys
import threading
import time

import numpy as np

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.agent import Agent, FramePose
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.gaussian_map import GaussianParams
from swarmsplat.slam.dense.packed import PackedRGBD, pack
from swarmsplat.slam.dense.submaps import Keyframe, retire_keyframes
from swarmsplat.kernels.memory import trim_heap


class MappingStopped(Exception):
    """The worker was stopped (end of the run, Ctrl-C) in the middle of a keyframe."""


class RealtimeAgent(Agent):
    def __init__(self, camera, cfg: SlamConfig | None = None, *, name: str = "agent"):
        super().__init__(camera, cfg, name=name)
        self._published = GaussianParams.empty()  # what the tracker aligns to (the active submap's, mapped)
        self._handover = None  # (submap id, params, view, keyframe frame, T_local_kf) from the worker
        self._lock = threading.Lock()
        self._idle = threading.Event()
        self._idle.set()
        self._pending = threading.Event()  # a keyframe waits for the worker
        self._stop = threading.Event()
        self._job = None  # (keyframe, odometry information, frame) for the worker
        self._due = None  # (index, timestamp, frame) of the frame just posed when it is to be handed over
        self._cv = threading.Condition()
        self.error: BaseException | None = None  # what ended the worker, raised on the tracker's thread
        self.keyframes_deferred = 0  # frames due to be keyframes while the worker was busy
        self._late = None  # the first deferred frame since the last keyframe or late view: a late view to be
        self.mapping_log: list[dict] = []  # per keyframe: iterations, planned, seconds (mapping, loop closure)
        self.worker_cpu_s = 0.0  # CPU time of the worker thread
        self._thread = threading.Thread(target=self._work, name=f"{name}-mapping", daemon=True)
        self._thread.start()

    # ---- the tracker's thread -----------------------------------------------------------------------------------

    def step(self, index: int, timestamp: float, color: np.ndarray, depth: np.ndarray | None) -> FramePose | None:
        """Track one frame and hand its keyframe over (`track`, then `hand_over_keyframe`); returns its pose (None
        when it was skipped). Never waits for the map."""
        rec = self.track(index, timestamp, color, depth)
        self.hand_over_keyframe()
        return rec

    def prepare(self, frame) -> RGBD | None:
        """A dataset frame (index, color, depth) as `track` takes it (`prepared`), or None when it is skipped
        (too little valid depth; recorded): what the real-time feed does on its reader thread."""
        return self._prepare(frame.index, frame.color, frame.depth)

    def track(self, index: int, timestamp: float, color: np.ndarray | None, depth: np.ndarray | None, *,
              prepared: RGBD | None = None, deadline: float | None = None) -> FramePose | None:
        """Track one frame against the map published last and return its pose (None when it was skipped), at once:
        a keyframe it is due to be is handed over by `hand_over_keyframe`, after the pose went out. `prepared`:
        the frame as `prepare` made it (then color and depth are not read). `deadline`: the time.monotonic() value
        by which the pose is due; with runtime.skip_late_refinement the tracker leaves its refinement out when it
        would end later (slam.dense.tracking.tracker Tracker.deadline)."""
        if self.error is not None:
            raise self.error
        self._due = None
        frame = prepared if prepared is not None else self._prepare(index, color, depth)
        if frame is None:
            return None
        self._take_handover()
        t0 = time.perf_counter()
        self.tracker.deadline = deadline if self.cfg.runtime.skip_late_refinement else None
        try:
            T_local_cam = self._track(frame, index)
        finally:
            self.tracker.deadline = None
        self.time.tracking += time.perf_counter() - t0
        if self._is_keyframe(T_local_cam):
            if self._idle.is_set():
                self._due = (index, timestamp, frame)
            else:
                self.keyframes_deferred += 1
                self._pending.set()
                if self.cfg.runtime.late_views and self.keep_keyframe_images:  # the refinement fits them
                    self._defer(index, timestamp, frame, T_local_cam)
        self.time.frames += 1
        rec = FramePose(index, timestamp, self.gmap.active.id if self.gmap.submaps else -1, T_local_cam)
        self.poses.append(rec)
        if rec.submap_id < 0:  # the first frame: its pose is in the frame of the submap it starts
            self.hand_over_keyframe()
        return rec

    def _defer(self, index: int, timestamp: float, frame: RGBD, T_local_cam: np.ndarray) -> None:
        """A frame due to be a keyframe while the worker is busy: the first such frame since the last keyframe is
        held as a late view candidate (config runtime.late_views); one held keyframes.every frames ago, with the
        keyframe still waiting, becomes a late view and this frame the next candidate."""
        if self._late is not None and index - self._late.frame_index < self.cfg.keyframes.every:
            return
        self._commit_late()
        # The frame as tracked, not a copy: it is brought to the mapping resolution and packed on the worker, with
        # its submap's keyframes, or at the end of the stream (_fit_late), not here on the tracker's time. Its
        # images stand for the small ones too: a late view is never registered.
        self._late = Keyframe(-1 - len(self.late_views), index, timestamp, self.gmap.active.id, T_local_cam.copy(),
                              frame, frame)

    def _commit_late(self, next_keyframe: int | None = None) -> None:
        """The held candidate becomes a late view unless the keyframe it waited for (frame `next_keyframe`) came
        within half of keyframes.every frames of it: that keyframe then sees nearly what it saw."""
        lv, self._late = self._late, None
        if lv is None or (next_keyframe is not None
                          and next_keyframe - lv.frame_index < max(1, self.cfg.keyframes.every // 2)):
            return
        self.late_views.append(lv)

    def end_stream(self) -> None:
        """After the last frame (the worker stopped): the late view candidate still held becomes one, and every
        late view not packed yet is brought to the mapping resolution."""
        self._commit_late()
        for lv in self.late_views:
            self._fit_late(lv, pack_it=False)

    def _fit_late(self, lv: Keyframe, *, pack_it: bool) -> None:
        """A late view's images at the mapping resolution, as a keyframe's map_rgbd (packed with `pack_it`)."""
        if isinstance(lv.map_rgbd, PackedRGBD):
            return
        m = lv.map_rgbd.resized(self.cfg.mapping.max_width)
        lv.map_rgbd = lv.small = pack(m) if pack_it else m

    def hand_over_keyframe(self) -> None:
        """When the frame `track` posed last is due to be a keyframe (and the worker was idle): start a submap if
        needed, add the keyframe and hand it to the worker. The frame's pose record moves to the new submap's frame
        then; its world pose stays what was emitted."""
        if self._due is None:
            return
        (index, timestamp, frame), self._due = self._due, None
        self._commit_late(index)
        rec = self.poses[-1]
        rec.T_local_cam = self._hand_over(index, timestamp, frame, rec.T_local_cam)
        rec.submap_id = self.gmap.active.id

    def _tracking_params(self) -> GaussianParams:
        return self._published

    def _take_handover(self) -> None:
        with self._lock:
            h, self._handover = self._handover, None
        if h is None or not self.gmap.submaps or h[0] != self.gmap.active.id:
            return
        _, params, view, kf_frame, T_kf = h
        self._published = params
        if view is not None:
            self.tracker.use_view(view, kf_frame, T_kf)

    def _hand_over(self, index: int, timestamp: float, frame: RGBD, T_local_cam: np.ndarray) -> np.ndarray:
        before = self.gmap.active.id if self.gmap.submaps else None
        # A retired submap's keyframe images are packed and its Gaussians encoded for the map's store on the worker
        # (_retire; tens of ms each), not here between two frames.
        compress, self.compress_keyframes = self.compress_keyframes, False
        store, self.gmap.store = self.gmap.store, None
        frame_store, self.frame_store = self.frame_store, None
        try:
            T_local_cam = self._maybe_start_submap(T_local_cam)
        finally:
            self.compress_keyframes, self.gmap.store, self.frame_store = compress, store, frame_store
        retired = None
        if self.gmap.active.id != before:
            self._published = self.gmap.active.params  # a new submap: nothing mapped in it yet
            if before is not None:
                retired = (before, [k for k in self.keyframes if k.submap_id == before] if compress else [])
        kf = self._add_keyframe(index, timestamp, frame, T_local_cam, exposure_now=False)  # fitted on the worker
        information = self._chain.information()
        self._chain.reset()
        self._idle.clear()
        self._pending.clear()
        with self._cv:
            self._job = (kf, information, frame, retired)
            self._cv.notify()
        return T_local_cam

    def idle(self) -> bool:
        return self._idle.is_set()

    def finish(self, timeout: float | None = None) -> bool:
        """Let the worker finish its keyframe (`timeout` s at most; None: as long as it takes), then stop it.
        Returns True when it had finished."""
        done = self._idle.wait(timeout)
        self.stop(0.0 if done else 1.0)
        if self.error is not None and not isinstance(self.error, MappingStopped):
            raise self.error
        return done

    def stop(self, timeout: float = 1.0) -> None:
        """Stop the worker: it ends its keyframe's optimisation at the next iteration and exits (waits `timeout`
        s for it)."""
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout)

    # ---- the worker's thread ------------------------------------------------------------------------------------

    def _work(self) -> None:
        _lower_priority(self.cfg.runtime.mapping_nice)
        c0 = time.thread_time()
        try:
            while True:
                with self._cv:
                    while self._job is None and not self._stop.is_set():
                        self._cv.wait(0.1)
                    if self._stop.is_set():
                        return
                    job, self._job = self._job, None
                self._keyframe(*job)
                self.worker_cpu_s = time.thread_time() - c0
                self._idle.set()
        except MappingStopped:
            pass
        except BaseException as e:  # noqa: BLE001 - raised on the tracker's thread at its next step
            self.error = e
        finally:
            self.worker_cpu_s = time.thread_time() - c0
            self._idle.set()

    def _keyframe(self, kf: Keyframe, information, frame: RGBD, retired: tuple[int, list[Keyframe]] | None) -> None:
        rt = self.cfg.runtime
        t0 = time.perf_counter()
        if retired is not None:
            self._retire(*retired)
        # the keyframe's exposure, from the map as it stands (rendering one or more submaps: up to ~0.2 s, which on
        # the tracker's thread made it drop the frames behind it)
        self._keyframe_exposure(kf)
        first = len(self.gmap.submaps[kf.submap_id].keyframe_ids) == 1
        planned = rt.max_mapping_iterations or (self.cfg.mapping.first_iterations if first else
                                                self.cfg.mapping.iterations)

        def stop(i: int) -> bool:
            return self._stop.is_set() or (i >= rt.min_mapping_iterations and self._pending.is_set())

        stats = self._map(kf, iterations=planned, stop=stop)
        if self._stop.is_set():
            raise MappingStopped
        params = self.gmap.submaps[kf.submap_id].params
        view = None
        tc = self.cfg.tracking
        if tc.refine and tc.method == "gauss_newton" and tc.iterations > 0 and len(params):
            view = self.tracker.build_view(params, frame.resized(tc.refine_max_width).camera, frame, kf.T_local_cam,
                                           kf.exposure)
        with self._lock:
            self._handover = (kf.submap_id, params, view, frame, kf.T_local_cam)
            self.tracker.exposure = kf.exposure  # a view the tracker renders itself shows this camera's exposure
        t1 = time.perf_counter()
        self._detect_loops(kf, information)
        t2 = time.perf_counter()
        self.time.mapping += t1 - t0
        self.time.loop_closure += t2 - t1
        self.mapping_log.append({"keyframe": kf.id, "frame": kf.frame_index, "iterations": stats.iterations,
                                 "planned": planned, "mapping_s": t1 - t0, "loop_closure_s": t2 - t1})

    def _retire(self, submap_id: int, keyframes: list[Keyframe]) -> None:
        """What slam.dense.submaps.start_submap does to the submap it retires, with the map's store and `compress`:
        pack its keyframes' images (lossless, so reads are unchanged), move them to the agent's frame store if it
        has one, and move its Gaussians to the map's store. (start_submap has dropped the mapping-resolution
        images already where they are not kept.)"""
        retire_keyframes(keyframes, keep_images=True, compress=True, frame_store=self.frame_store)
        for lv in list(self.late_views):  # the late views of finished submaps, packed as their keyframes are
            if lv.submap_id != self.gmap.active.id:
                self._fit_late(lv, pack_it=True)
        self.gmap.retire(self.gmap.submaps[submap_id])
        if self.cfg.kernels.malloc_trim:
            trim_heap()


def _lower_priority(nice: int) -> None:
    """Add `nice` to the calling thread's nice value (Linux keeps one per thread; elsewhere nothing happens). The
    Warp launch pool runs a thread's kernel parts on pool threads of the same nice value (kernels/_warp/launch.py),
    so the mapping worker's parts never queue in front of the tracker's either."""
    if nice <= 0 or not sys.platform.startswith("linux"):
        return
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    except OSError:
        pass  # not allowed here: the worker keeps the tracker's priority
