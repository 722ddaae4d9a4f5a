"""Video tracks decoded with PyAV, frame by frame, with damaged frames told apart.

A frame is damaged when FFmpeg fails on its packet, flags it corrupt, or logs an error while
decoding it (the decoders are asked to stop at the first error, ``err_detect=explode``,
rather than conceal it); failing all that, when its bottom rows are one flat colour that
the rows above are not (what a decoder that ran out of data fills the rest with). A file
ends early when its packets stop before the frame count its header announces, when its
demuxer fails mid-way, or when its frames stop well before the duration its header gives
(Matroska writes it whole at the start). FFmpeg's own lines never reach the terminal: its
log goes to PyAV's capture, and file descriptor 2 is shut meanwhile for anything printed
past it.

:func:`open_video` reads a plain video (``.mp4 .avi .mkv .mov .webm``: no calibration, no
depth); :mod:`.kinect` reads its tracks with :func:`index_tracks` and :func:`decode_tracks`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.ingest.readers import RecorderReader
from annotator.ingest.recording import Decoded, Recording
from annotator.io.images import native_stderr_hidden

#: Rows at the bottom that are one flat colour, as a share of the height, that mark a frame
#: the decoder filled in.
FLAT_BAND = 0.08


@dataclass(frozen=True)
class TrackIndex:
    """One video track's frames, from its packets (nothing decoded).

    Attributes:
        stream: The track's stream index.
        pts: Each frame's presentation time stamp (in ``time_base``), in order.
        time_base: Seconds per unit of ``pts``.
        announced: The frame count the header gives (0 if none).
    """

    stream: int
    pts: list[int]
    time_base: float
    announced: int

    @property
    def times(self) -> list[float]:
        """Each frame's time (s)."""
        return [p * self.time_base for p in self.pts]


@contextlib.contextmanager
def quiet_ffmpeg() -> Iterator[list[tuple[int, str, str]]]:
    """FFmpeg's log lines of the block, captured (not printed); descriptor 2 shut meanwhile."""
    import av.logging

    before = av.logging.get_level()
    av.logging.set_level(av.logging.WARNING)
    try:
        with native_stderr_hidden(), av.logging.Capture(local=False) as logs:
            yield logs
    finally:
        av.logging.set_level(before)


def _open(path: Path) -> Any:
    import av

    try:
        with quiet_ffmpeg():
            return av.open(str(path))
    except (av.error.FFmpegError, OSError, UnicodeDecodeError) as exc:
        raise UserError(f"not a readable video ({_reason(exc)})", path=path) from None


def _reason(exc: BaseException) -> str:
    text = str(getattr(exc, "strerror", None) or exc)
    return text.split(";")[0].split(":")[0].strip() or type(exc).__name__


def index_tracks(path: Path, streams: Sequence[int]) -> tuple[dict[int, TrackIndex], str | None]:
    """The frames of the tracks ``streams`` from their packets, and why the file ends early
    (None if it does not)."""
    import av

    container = _open(path)
    pts: dict[int, list[int]] = {s: [] for s in streams}
    ended: str | None = None
    try:
        chosen = [container.streams[s] for s in streams]
        with quiet_ffmpeg():
            try:
                for pkt in container.demux(chosen):
                    if pkt.size == 0 or pkt.pts is None and pkt.dts is None:
                        continue  # the flush packet at the end
                    pts[pkt.stream.index].append(int(pkt.pts if pkt.pts is not None else pkt.dts))
            except (av.error.FFmpegError, OSError) as exc:
                ended = f"the file is cut or damaged after that ({_reason(exc)})"
        out = {}
        for s in chosen:
            base = float(s.time_base) if s.time_base else 0.0
            out[s.index] = TrackIndex(s.index, sorted(set(pts[s.index])), base, int(s.frames or 0))
        duration = container.duration / 1e6 if container.duration else None
    finally:
        container.close()
    if ended is None and duration is not None:
        ended = _short_of(out.values(), duration)
    for t in out.values():
        if t.announced and len(t.times) < t.announced:
            ended = (
                f"the file ends early or lost frames: it holds {len(t.pts)} of the "
                f"{t.announced} frames its header announces (a frame's index and time after "
                "a lost one may be short by the frames lost)"
            )
    return out, ended


def _short_of(tracks: Iterable[TrackIndex], duration_s: float) -> str | None:
    """Why frames stop before the duration the header gives (a file cut short whose header,
    as Matroska's, was written whole), or None."""
    for t in tracks:
        times = t.times
        if len(times) < 2:
            continue
        step = float(np.median(np.diff(times)))
        covered = times[-1] - times[0] + step
        if step > 0 and covered + 1.5 * step < duration_s:
            return (
                f"the file ends early: its frames stop at {covered:.3f} s of the "
                f"{duration_s:.3f} s its header gives"
            )
    return None


def decode_tracks(
    path: Path, wanted: dict[int, set[int]], index: dict[int, TrackIndex], formats: dict[int, str]
) -> Iterator[tuple[int, int, np.ndarray | None, str | None]]:
    """Decode the frames ``wanted[stream]`` (frame indices in :class:`TrackIndex` order) of
    each track, in file order: ``(stream, frame index, pixels or None, problem or None)``;
    pixels as ``formats[stream]`` (``bgr24``, ``gray16``...)."""

    container = _open(path)
    try:
        chosen = [container.streams[s] for s in wanted]
        rank: dict[int, dict[int, int]] = {}
        for s in chosen:
            rank[s.index] = {p: k for k, p in enumerate(index[s.index].pts)}
            s.codec_context.options = {"err_detect": "crccheck+bitstream+buffer+explode"}
            s.thread_type = "NONE"
        packets = container.demux(chosen)
        while True:
            # FFmpeg is silenced packet by packet, not across the yields: the progress bar
            # and anything else the caller prints meanwhile must reach the terminal.
            with quiet_ffmpeg() as logs:
                step = _next_packet(packets)
                if step is None:
                    break
                pkt, frames, error = step
                trouble = _trouble(logs)
                out: list[tuple[int, int, np.ndarray | None, str | None]] = []
                sid = pkt.stream.index
                if error is not None:
                    key = pkt.pts if pkt.pts is not None else pkt.dts
                    k = rank[sid].get(int(key)) if key is not None else None
                    if k is not None and k in wanted[sid]:
                        out.append((sid, k, None, f"fails to decode ({error})"))
                for frame in frames:
                    k = rank[sid].get(int(frame.pts)) if frame.pts is not None else None
                    if k is not None and k in wanted[sid]:
                        out.append(_checked(sid, k, frame, formats[sid], trouble))
            yield from out
    finally:
        container.close()


def _next_packet(packets: Iterator[Any]) -> tuple[Any, list[Any], str | None] | None:
    """The next packet, its frames and why it failed to decode (None at the end, or where
    the demuxer fails: :func:`index_tracks` said so already)."""
    import av

    try:
        pkt = next(packets)
    except (StopIteration, av.error.FFmpegError, OSError):
        return None
    try:
        return pkt, list(pkt.decode()), None
    except (av.error.FFmpegError, ValueError) as exc:
        return pkt, [], _reason(exc)


def _checked(
    sid: int, k: int, frame: Any, fmt: str, trouble: str | None
) -> tuple[int, int, np.ndarray | None, str | None]:
    """A decoded frame's pixels, or why it decoded only partly."""
    if frame.is_corrupt or trouble:
        return sid, k, None, f"decodes partly ({trouble or 'flagged corrupt'})"
    pixels = _pixels(frame, fmt)
    band = flat_band(pixels) if pixels.dtype == np.uint8 else None
    if band:
        return sid, k, None, f"decodes partly ({band})"
    return sid, k, pixels, None


def _trouble(lines: Sequence[tuple[int, str, str]]) -> str | None:
    """The first error FFmpeg logged for a packet (None if none)."""
    import av.logging

    for level, _, message in lines:
        low = message.lower()
        if level <= av.logging.ERROR or any(w in low for w in ("corrupt", "overread", "missing")):
            return message.strip()
    return None


def _pixels(frame: Any, fmt: str) -> np.ndarray:
    if fmt == "gray16":
        return np.asarray(frame.to_ndarray(), np.uint16)  # native order whatever the file's
    return np.ascontiguousarray(frame.to_ndarray(format="bgr24"))


def flat_band(img: np.ndarray) -> str | None:
    """What a decoder that ran out of data leaves: the bottom rows one flat colour (a band at
    least :data:`FLAT_BAND` of the height) above which the image is not flat. None if not,
    and None for a black or white band, or one matched by a band at the top (a letterbox,
    or an image dark or burnt out at its edge, not a decoder's filling).

    >>> img = np.random.default_rng(0).integers(0, 255, (50, 40, 3), np.uint8)
    >>> flat_band(img) is None
    True
    >>> img[40:] = (255, 0, 255)
    >>> flat_band(img)
    'the bottom 10 rows are one flat colour'
    >>> img[40:] = 0
    >>> flat_band(img) is None
    True
    """
    h = img.shape[0]
    rows = img.reshape(h, -1, img.shape[2] if img.ndim == 3 else 1).astype(np.int16)
    first = rows[-1, 0]
    if np.all(first <= 16) or np.all(first >= 240):
        return None
    n = _flat_run(np.all(np.abs(rows - first) <= 2, axis=(1, 2))[::-1])
    if n < max(2, FLAT_BAND * h) or n >= h:
        return None
    top = _flat_run(np.all(np.abs(rows - rows[0, 0]) <= 2, axis=(1, 2)))
    if top >= n / 2:
        return None
    return f"the bottom {n} rows are one flat colour"


def _flat_run(flat: np.ndarray) -> int:
    """How many leading entries are True."""
    return int(np.argmin(flat)) if not flat.all() else len(flat)


@dataclass
class _VideoRecording(Recording):
    track: TrackIndex | None = None

    def decode(self, indices: Sequence[int], *, depth: bool) -> Iterator[Decoded]:
        assert self.track is not None
        sid = self.track.stream
        tracks = {sid: self.track}
        for _, k, img, problem in decode_tracks(
            self.path, {sid: set(indices)}, tracks, {sid: "bgr24"}
        ):
            yield Decoded(k, img, None, problem)


def open_video(path: Path) -> Recording:
    """A plain video's frames (its first video track), with their times from the container."""
    container = _open(path)
    try:
        video = [s for s in container.streams if s.type == "video"]
        if not video:
            raise UserError("not a readable video (no video track)", path=path)
        sid = video[0].index
    finally:
        container.close()
    tracks, ended = index_tracks(path, [sid])
    times = tracks[sid].times
    if not times:
        raise UserError("not a readable video (no frame could be decoded)", path=path)
    return _VideoRecording(
        path=path,
        kind="video",
        times=[t - times[0] for t in times],
        labels=list(range(len(times))),
        depth_for=[None] * len(times),
        streams={"colour": f"video track {sid}"},
        ended_early=ended,
        track=tracks[sid],
    )


#: The file types read as plain videos.
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".webm")

READERS = (
    RecorderReader(
        "video",
        VIDEO_SUFFIXES,
        lambda path, _: path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES,
        lambda path, _: open_video(path),
        order=40,
    ),
)
