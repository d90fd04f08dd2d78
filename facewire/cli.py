"""``facewire``: the command-line contract of docs/DESIGN.md §7, parsed and dispatched.

Every subcommand of the contract is listed by ``facewire --help``. Errors a user can cause
(a ``FacewireError`` of any part, see ``protocol/errors.py``, or a file the system will not
open) print one clear line to stderr, ``facewire: MESSAGE``, and exit with status 2; a
benchmark whose target is missed exits with status 1.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeAlias, TypeVar

from facewire.protocol.errors import FacewireError
from facewire.protocol.opus import DEFAULT_BITRATE
from facewire.protocol.rate import MAX_RATE_HZ, MIN_RATE_HZ, NOMINAL_HZ

EXIT_USAGE = 2
# The failures a user can cause: reported as one line, no traceback.
USER_ERRORS = (FacewireError, FileNotFoundError, PermissionError, IsADirectoryError)
T = TypeVar("T")
Commands: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"


class CommandError(FacewireError):
    """A bad command-line argument (e.g. ``--size``, ``--frames``)."""


def _replay(args: argparse.Namespace) -> int:
    from facewire.receiver.replay import replay_log
    from facewire.report import report

    s = replay_log(args.log, args.model, args.out, args.view, _size(args.size), args.side_by_side,
                   progress=_progress)
    report(s, [f"wrote {s['out']}: {s['frames']} frames ({s['width']}x{s['height']}, "
               f"{s['view']} view)",
               f"packets: {s['received']} received, {s['concealed']} slots concealed, "
               f"{s['corrupt']} corrupt, {s['duplicate']} duplicate, {s['late']} late; "
               f"{s['lost_records']} damaged log records",
               *_replay_updates(s),
               *([f"sound: {s['sound_s']} s from {s['voice_frames']} voice packets"]
                 if s["voice_frames"] else []),
               f"render: {s['render_fps']} fps; {s['seconds']} s in all"], args.json)
    return 0


def _replay_updates(s: dict[str, Any]) -> list[str]:
    """``replay``'s line on the model updates, none for a log without any."""
    if not (s["updates"] or s["lost_updates"] or s["missing_serials"]):
        return []
    line = (f"model updates: {s['updates_applied']} of {s['updates']} in the log applied, "
            f"{s['lost_updates']} damaged")
    if s["missing_serials"]:
        line += (f"; lacking serials {', '.join(map(str, s['missing_serials']))}: "
                 f"{s['clamped_frames']} frames shown clamped to the layers held")
    return [line]


def _rate(text: str) -> float:
    """``--rate``: a frame rate a Hello may announce (``protocol.rate``), else a usage error."""
    try:
        rate = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of Hz, got {text!r}") from None
    if not MIN_RATE_HZ <= rate <= MAX_RATE_HZ:
        raise argparse.ArgumentTypeError(
            f"expected {MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} Hz, got {text}")
    return rate


def _send(args: argparse.Namespace) -> int:
    from facewire.protocol.rate import over_budget_warning
    from facewire.protocol.transport import unencrypted_warning
    from facewire.report import report
    from facewire.sender.sender import send

    for warning in (unencrypted_warning(args.bind, args.curve_dir) if args.insecure else None,
                    over_budget_warning(args.rate)):
        if warning is not None:
            print(f"facewire send: {warning}", file=sys.stderr)
    banner = [f"facewire send: publishing on {args.bind} (control on the next port); "
              f"Ctrl-C stops"]

    def status(t: dict) -> str:
        """The live status line; the banner before the first one, once the sockets are
        bound and frames flow (a refused model, source or address is the only line)."""
        while banner:
            print(banner.pop(), file=sys.stderr)
        return (f"{t['seconds']:7.1f} s  {t['fps']:5.1f} fps  {t['payload_kbps']:5.2f} "
                f"kbit/s  face {'yes' if t['face'] else 'no '}  receivers {t['receivers']}  "
                f"updates {t['updates']}")

    with _StatusLine(status) as line:
        s = send(args.model, args.source, args.bind, args.record, args.rate, args.curve_dir,
                 status=line, loop=args.loop, learn=not args.no_learn,
                 insecure=args.insecure,
                 warn=lambda text: print(f"facewire send: {text}", file=sys.stderr),
                 audio=not args.no_audio, mic=args.mic,
                 voice_bitrate=round(args.voice_kbps * 1000))
    report(s, [f"sent {s['packets']} packets from {s['frames']} frames ({s['face_frames']} "
               f"with a face) in {s['seconds']} s: {s['fps']} fps, {s['payload_kbps']} "
               f"kbit/s payload, at most {s['receivers_max']} receivers, {s['updates']} model "
               f"updates learned",
               f"model {s['model_sha256'][:16]}... ({s['model_bytes']} bytes, "
               f"{s['model_chunks']} chunks), {s['updates']} model updates "
               f"({s['update_bytes_total']} bytes; {s['control']['update_bytes']} bytes of "
               f"update chunks served); stopped: {s['stopped']}"
               + (f"; log: {s['log']}" if s["log"] else ""),
               *([f"voice ({s['voice']}): {s['voice_packets']} packets, {s['audio_kbps']} "
                  f"kbit/s"] if s["voice"] else [])], args.json)
    return 0


def _receive(args: argparse.Namespace) -> int:
    from contextlib import nullcontext

    from facewire.receiver.liveview import LiveView
    from facewire.receiver.receiver import receive
    from facewire.report import report

    with LiveView(args.view_port) if args.view else nullcontext() as live:
        view = None
        if live is not None:
            print(f"facewire receive: live view at {live.url}", file=sys.stderr)
            view = live.show

        stop = threading.Event()
        previous = signal.signal(signal.SIGINT, lambda *_: stop.set())  # Ctrl-C: clean stop
        try:
            with _StatusLine(lambda line: line) as line:
                s = receive(args.connect, args.model, args.out, args.frames, view,
                            args.curve_dir, size=_size(args.size), status=line, stop=stop,
                            idle_timeout_s=args.idle_timeout, audio=not args.no_audio,
                            speaker=args.speaker or "", keep_up=args.keep_up)
        finally:
            signal.signal(signal.SIGINT, previous)
    if s["model_sha256"] is None:
        report(s, [f"no sender answered at {args.connect}; ended: {s['ended']}"], args.json)
        return 0
    report(s, [f"received {s['received']} packets ({s['kbps']} kbit/s): {s['lost']} lost, "
               f"{s['late']} late, {s['corrupt']} corrupt, {s['duplicates']} duplicates; "
               f"{s['restarts']} resyncs (sender restarts, or falling behind)",
               f"rendered {s['frames']} frames at {s['fps']} fps ({s['width']}x{s['height']}"
               f"{'; ' + str(s['repeated']) + ' repeated' if s['repeated'] else ''}); "
               f"latency {s['latency_ms_median']} ms median, {s['latency_ms_p95']} ms p95; "
               f"glass-to-glass {s['glass_to_glass_ms_median']} ms median, "
               f"{s['glass_to_glass_ms_p95']} ms p95",
               f"model {s['model_sha256'][:16]}... ({s['model_source']}"
               + (f", {s['model_bytes']} bytes in {s['model_fetch_s']} s" if s["model_fetch_s"]
                  else "") + ")"
               + (f"; wrote {s['out']}" if s["out"] else "") + f"; ended: {s['ended']}",
               f"model version {s['model_serial']}: {s['updates']} updates applied "
               f"({s['update_bytes']} bytes), {s['updates_refused']} refused; {s['clamped']} "
               f"slots rendered before their update came (Q clamped)",
               *([f"voice on {s['speaker']}: {s['voice_received']} packets "
                  f"({s['audio_kbps']} kbit/s), {s['voice_played']} played, "
                  f"{s['voice_recovered']} rebuilt, {s['voice_concealed']} concealed, "
                  f"{s['voice_late']} late, {s['voice_corrupt']} corrupt; sound behind the "
                  f"face by {s['av_skew_ms_median']} ms median ({s['av_skew_ms_p5']} to "
                  f"{s['av_skew_ms_p95']} ms, 5-95 %)"] if s.get("voice_received") else [])],
           args.json)
    return 0


def _call(args: argparse.Namespace) -> int:
    from facewire.call import call
    from facewire.report import report

    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())  # Ctrl-C: hang up
    try:
        with _StatusLine(lambda line: line) as line:
            s = call(args.model, args.source, args.peer, args.bind, args.curve_dir, args.mic,
                     args.speaker or "", not args.no_audio, args.loop, args.view_port,
                     args.insecure, args.idle_timeout, stop, args.out,
                     say=lambda text: print(f"facewire call: {text}", file=sys.stderr),
                     status=line, voice_bitrate=round(args.voice_kbps * 1000),
                     learn=not args.no_learn)
    finally:
        signal.signal(signal.SIGINT, previous)
    sent, got = s["send"], s["receive"]
    report(s, [f"sent: {sent.get('frames', 0)} frames, {sent.get('voice_packets', 0)} voice "
               f"packets ({sent.get('payload_kbps', 0)} + {sent.get('audio_kbps', 0)} kbit/s)",
               f"received: {got.get('received', 0)} packets, {got.get('lost', 0)} lost; "
               f"{got.get('voice_received', 0)} voice packets, "
               f"{got.get('voice_concealed', 0)} concealed; sound behind the face by "
               f"{got.get('av_skew_ms_median')} ms median; ended: {got.get('ended')}"],
           args.json)
    return 0 if "error" not in sent else 1


def _size(text: str | None) -> tuple[int, int] | None:
    """``--size WxH`` as (width, height), or None."""
    if text is None:
        return None
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CommandError(f"--size: expected WxH, e.g. 1280x720, got {text!r}") from None
    return width, height


def _relay(args: argparse.Namespace) -> int:
    from facewire.protocol.relay import relay
    from facewire.protocol.transport import check_plaintext, control_endpoint, unencrypted_warning
    from facewire.report import report

    for endpoint in (args.inp, args.out):  # refused in one line, before the banner
        control_endpoint(endpoint)
    check_plaintext(args.out, args.curve_out, args.insecure)
    warning = unencrypted_warning(args.out, args.curve_out) if args.insecure else None
    if warning is not None:
        print(f"facewire relay: {warning}", file=sys.stderr)
    print(f"facewire relay: {args.inp} -> {args.out} (control on the next ports); Ctrl-C "
          f"stops", file=sys.stderr)
    s = relay(args.inp, args.out, curve_in=args.curve_in, curve_out=args.curve_out,
              insecure=args.insecure)
    report(s, [f"relayed {s['packets']} packets and {s['reply_bytes']} bytes of control "
               f"replies in {s['seconds']} s; stopped: {s['stopped']}"], args.json)
    return 0


def _web(args: argparse.Namespace) -> int:
    from facewire.receiver.gateway import (
        DEFAULT_HTTP,
        TOKEN_ENV,
        check_hosts,
        check_token,
        new_token,
        parse_http,
        read_token_file,
        remote_warning,
        serve_gateway,
        shown_url,
    )
    from facewire.report import report

    http = args.http or DEFAULT_HTTP
    host, _ = parse_http(http, args.allow_remote)
    hosts = tuple(args.host or ())
    check_hosts(hosts, args.allow_remote)
    warning = remote_warning(host)
    if warning is not None:
        print(f"facewire web: {warning}", file=sys.stderr)
    opener: Path | None = None
    if args.token is not None:
        check_token(args.token)
        print("facewire web: warning: --token shows the token to every user of this machine "
              f"(ps); use --token-file FILE or {TOKEN_ENV}", file=sys.stderr)
        token, where = args.token, "--token"
    elif args.token_file is not None:
        token, where = read_token_file(args.token_file), args.token_file
    elif os.environ.get(TOKEN_ENV):
        token, where = os.environ[TOKEN_ENV], TOKEN_ENV
        check_token(token, TOKEN_ENV)
    else:
        token, where = new_token(), None

    def opened(url: str) -> None:
        nonlocal opener
        if where is not None:
            say(f"open {shown_url(url)} with the token of {where} (Ctrl-C stops)")
            return
        opener = _page_opener(url)
        say(f"open file://{opener} : it opens {shown_url(url)} with its token, made for this "
            f"run (Ctrl-C stops)")

    def status(t: dict) -> str:
        return (f"{t['seconds']:7.1f} s  sender {t['sender']}  model {t['model'] or '-'} "
                f"v{t['version']}  viewers {t['viewers']}  packets {t['forwarded']}  corrupt "
                f"{t['corrupt']}  dropped {t['dropped']}")

    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set())  # Ctrl-C, kill: clean stop
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with _StatusLine(status) as line:
            def say(text: str) -> None:
                """An event: a line of its own above the status line."""
                print("\r" + f"facewire web: {text}".ljust(line.width), file=sys.stderr,
                      flush=True)
                line.width = 0

            s = serve_gateway(args.connect, http, args.curve_dir, token, args.allow_remote,
                              stop=stop, say=say, status=line, ready=opened, hosts=hosts)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if opener is not None:
            opener.unlink(missing_ok=True)
    report(s, [f"forwarded {s['forwarded']} packets ({s['corrupt']} corrupt dropped, "
               f"{s['held']} before a model) in {s['seconds']} s to at most {s['viewers_max']} "
               f"viewers ({s['viewers_total']} in all; cut off: {s['dropped_junk']} for junk, "
               f"{s['dropped_slow']} for not reading)",
               f"model {(s['model_sha256'] or '-')[:16]} version {s['model_serial']}; "
               f"{s['http_served']} files served, {s['http_refused']} requests refused"],
           args.json)
    return 0


def _page_opener(url: str) -> Path:
    """A private (0600) HTML file that sends a browser to ``url``: the way to the page whose
    token is shown nowhere."""
    import html
    import tempfile

    fd, name = tempfile.mkstemp(prefix="facewire-web-", suffix=".html")
    link = html.escape(url)
    with os.fdopen(fd, "w", encoding="utf-8") as file:
        file.write(f'<!doctype html><meta charset="utf-8"><meta http-equiv="refresh" '
                   f'content="0; url={link}"><a href="{link}">facewire web</a>\n')
    return Path(name)


class _StatusLine:
    """A live status: one line of stderr rewritten in place by each call."""

    def __init__(self, render: Callable[[Any], str]) -> None:
        self.render = render
        self.width = 0

    def __call__(self, status: Any) -> None:
        text = self.render(status)
        print("\r" + text.ljust(self.width), end="", file=sys.stderr, flush=True)
        self.width = len(text)

    def __enter__(self) -> _StatusLine:
        return self

    def __exit__(self, *_: object) -> None:
        if self.width:
            print(file=sys.stderr)


def _demo(args: argparse.Namespace) -> int:
    from facewire.demo import demo
    from facewire.report import report

    r = demo(args.out, args.source, args.seconds, progress=_progress,
             status=lambda line: print(f"facewire demo: {line}", file=sys.stderr))
    s = r.summary()
    report(s, [f"video:     {s['video']} (performer | reconstruction, {s['frames']} frames)",
               f"bandwidth: {s['bandwidth_plot']}: {s['payload_kbps']} kbit/s payload, "
               f"{s['wire_kbps']} on the wire at 30 Hz ({s['packet_bytes']}-byte packets)",
               f"speed:     sender {s['sender_fps']} fps, receiver {s['output_fps']} fps "
               f"(rendering {s['render_fps']} fps, {s['packets_repeated']} frames repeated) "
               f"of the stream's {s['measured_rate_hz']} Hz; "
               f"latency {s['latency_ms_median']} ms median, {s['latency_ms_p95']} ms p95; "
               f"glass-to-glass {s['glass_to_glass_ms_median']} ms median, "
               f"{s['glass_to_glass_ms_p95']} ms p95",
               f"model:     {s['model']} ({s['model_bytes']} bytes, preview {s['preview']})",
               f"time:      {s['seconds']['total']} s"], args.json)
    return 0


def _inspect(args: argparse.Namespace) -> int:
    from facewire.bench.inspect import inspect_log
    from facewire.report import report

    report(*inspect_log(args.log, csv_path=args.csv), args.json)
    return 0


def _bench_bandwidth(args: argparse.Namespace) -> int:
    from facewire.bench.bandwidth import bandwidth
    from facewire.report import report

    summary, lines = bandwidth(args.log, plot=args.plot)
    report(summary, lines, args.json)
    return 0 if summary["under_limit"] else 1


def _keys_generate(args: argparse.Namespace) -> int:
    from facewire.protocol.keys import generate_keys

    public, secret = generate_keys(args.dir, name=args.name)
    print(f"public key:  {public}\nsecret key:  {secret}\n"
          f"authorised peers go in: {public.parent / 'authorized'}")
    return 0


def _progress(items: Iterable[T], label: str, total: int | None) -> Iterator[T]:
    """A progress bar on stderr, so that stdout keeps only the report."""
    from tqdm import tqdm

    return tqdm(items, desc=label, total=total, unit="frame", file=sys.stderr, leave=False)


def _frames(text: str | None) -> slice:
    """The ``--frames A:B`` option as a slice; a bad range is a one-line error."""
    from facewire.models.infra.video import frame_range

    try:
        return frame_range(text)
    except ValueError as exc:
        raise CommandError(str(exc)) from None


def _person(text: str | None) -> int | str | None:
    """``--person PHOTO|N``: an index (digits) or a photo's path, as given."""
    if text is None or not text.isdigit():
        return text
    return int(text)


def _model_build(args: argparse.Namespace) -> int:
    from facewire.report import report
    from facewire.sender.enroll.build import build_model, is_photo

    if sum(x is not None for x in (args.video, args.guided, args.from_log)) != 1:
        raise CommandError("model build: give one of VIDEO, PHOTO, --guided CAMERA or "
                           "--from-log LOG")
    if (args.model is None) != (args.from_log is None):
        raise CommandError("model build: --from-log LOG and --model BASE go together")
    if args.person is not None and args.video is None:
        raise CommandError("--person: chooses whom a VIDEO or PHOTO build is of")
    if args.guided is not None:
        return _model_build_guided(args)
    if args.from_log is not None:
        return _model_build_from_log(args)
    frames = _frames(args.frames)
    check = None
    if not args.no_self_check:
        from facewire.bench.selfcheck import photo_check, video_check

        check = photo_check(args.video, _progress) if is_photo(args.video) else \
            video_check(args.video, _progress)
    result = build_model(args.video, args.output, frames, progress=_progress, check=check,
                         person=_person(args.person))
    s = result.summary()
    person = [] if result.person is None else [result.person.line()]
    report(s, [*person, *_build_lines(s)], args.json)
    return 0


def _model_build_from_log(args: argparse.Namespace) -> int:
    """``model build --from-log LOG --model BASE``: the base with the session's model updates
    (``models.learned``)."""
    from facewire.models.learned import write_learned_model
    from facewire.report import report

    s = write_learned_model(args.from_log, args.model, args.output)
    grown = ", ".join(f"{name} {old} -> {new}" for name, (old, new) in s["layers"].items()
                      if old != new) or "none (states replaced)"
    lines = [f"model:    {s['path']} ({s['bytes']:,} bytes, sha256 {s['sha256'][:16]}...)",
             f"learned:  {len(s['applied'])} model updates of {s['log']} applied to "
             f"{s['base']} (sha256 {s['base_sha256'][:16]}...)",
             f"layers:   {grown}"]
    if s["left_out"] or s["missing_serials"]:
        lines.append(f"left out: updates {', '.join(map(str, s['left_out'])) or 'none'}; the "
                     f"log lacks serials {', '.join(map(str, s['missing_serials']))}")
    report(s, lines, args.json)
    return 0


def _model_build_guided(args: argparse.Namespace) -> int:
    """``model build --guided``: the routine recorded from a camera (or a video standing in),
    shown on the terminal and, with ``--view``, on the live page (``sender.enroll.guided``)."""
    from contextlib import nullcontext

    import numpy as np

    from facewire.receiver.liveview import LiveView
    from facewire.receiver.output import VideoWriter
    from facewire.report import report
    from facewire.sender.capture import open_source
    from facewire.sender.enroll.guided import Cue, build_guided, overlay
    from facewire.sender.enroll.routine import ROUTINE, Schedule

    if args.frames is not None:
        raise CommandError("--frames: a guided build records its own frames")
    try:
        schedule = Schedule(args.lead_seconds, args.prompt_seconds)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    check = None
    if not args.no_self_check:
        from facewire.bench.selfcheck import video_check

        def check(path: Any) -> Any:
            return video_check(path, _progress)

    with open_source(args.guided, pace=True if args.view else None) as source, \
            (LiveView(args.view_port) if args.view else nullcontext()) as live:
        if live is not None:
            print(f"facewire model build: live view at {live.url}", file=sys.stderr)
        print(f"facewire model build: {len(ROUTINE)} prompts, "
              f"{schedule.lead_s:g} s to get ready and {schedule.record_s:g} s recorded "
              f"each ({schedule.seconds:.1f} s); Ctrl-C stops", file=sys.stderr)
        with _StatusLine(lambda cue: cue.line()) as line:
            def say(text: str) -> None:
                if line.width:
                    print(file=sys.stderr)
                    line.width = 0
                print(text, file=sys.stderr, flush=True)

            def show(cue: Cue, image: np.ndarray) -> None:
                line(cue)
                if live is not None:
                    live.publish(overlay(image, cue), cue.stats())

            result = build_guided(source, args.output, VideoWriter, schedule, show, say,
                                  _progress, check)
    s = result.summary()
    takes = [f"          {k}. {t['text']}: frames {t['frames'][0]}:{t['frames'][1]}, "
             f"{t['face_frames']} with a face"
             + (f" ({t['tries']} takes: the face was lost)" if t["tries"] > 1 else "")
             for k, t in enumerate(s["guided"]["prompts"], 1)]
    report(s, [f"guided:   {s['guided']['source']}, {s['guided']['recorded_frames']} frames "
               f"recorded (built from a temporary H.264 file, deleted)", *takes,
               *_build_lines(s)], args.json)
    return 0


def _build_lines(s: dict[str, Any]) -> list[str]:
    """``model build``'s report from its summary (``BuildResult.summary``)."""
    regions = [f"          {name}: frames {r['frames']}, span {r['span']}"
               + (" (weak: the video barely shows it)" if r["weak"] else "")
               + (" (not all from its prompts: too few of their frames were usable)"
                  if r.get("prompted") is False else "")
               for name, r in s["appearance"].items()]
    return [f"model:    {s['path']} ({s['bytes']:,} bytes, sha256 {s['sha256'][:16]}...)",
            f"preview:  {s['preview']}",
            f"mesh:     {s['vertices']:,} vertices, {s['triangles']:,} triangles",
            f"frames:   {s['face_frames']} of {s['frames']} with a face; neutral frame "
            f"{s['neutral_frame']}; texture from frames {s['texture_views']}",
            f"hands:    on the face in {s['occluded_enrollment_frames']} of {s['frames']} "
            "frames (never the neutral nor a texture view)",
            "built from: " + (f"{s['source']['video']} frames {s['source']['start']}:"
                              f"{s['source']['stop']}" if s["source"] else
                              "a camera's recording (not kept)"),
            f"depth:    {s['depth']} (landmark depth changed {s['depth_change_mm']} mm RMS "
            f"from the generic head)",
            f"regions:  {s['regions']} with {s['layers']} layers (states chosen from frames)",
            *regions,
            _descriptors_line(s["descriptors"]),
            *_region_frames_lines(s["region_frames"]),
            *_coverage_lines(s["coverage"], s["coverage_lines"]),
            *_self_check_lines(s),
            f"time:     {s['seconds']} s"]


def _region_frames_lines(frames: dict[str, Any] | None) -> list[str]:
    """One line per region: the enrollment frames its layers used, and why the others were
    rejected (``sender.enroll.usage``); ``frames`` is the JSON's ``region_frames``."""
    if frames is None:
        return ["frames:   per region not recorded (a model without regions, or built before "
                "they were stored)"]
    from facewire.models.manifest import RegionFrames
    from facewire.sender.enroll.usage import usage_line

    return ["frames per region (used, rejected and why):",
            *(f"          {name}: "
              f"{usage_line(RegionFrames(f['candidates'], tuple(f['used']), f['rejected']))}"
              for name, f in frames.items())]


def _coverage_lines(coverage: dict[str, bool] | None, lines: list[str] | None = None
                    ) -> list[str]:
    """The report's coverage: a line naming the states the layers show, then one line per
    state they lack, saying what the rendering does instead (``sender.enroll.coverage``)."""
    if coverage is None:
        return ["coverage: not measured (a model built before coverage was stored)"]
    from facewire.sender.enroll.coverage import covered_line, missing_lines

    if lines is None:
        lines = missing_lines(coverage)
    return [f"coverage: {covered_line(coverage)}", *(f"          {line}" for line in lines)]


def _self_check_lines(s: dict[str, Any]) -> list[str]:
    """``model build``'s self-check lines (``bench.selfcheck``): the scores, then, when
    poor, the warning and its likely cause."""
    if "self_check_ssim" not in s:
        return ["self-check: skipped (--no-self-check)"]
    return [_self_check_text(s["self_check_ssim"], s["self_check_render_nme"],
                             s["self_check_frames"])
            + f" ({s['self_check_seconds']} s)",
            *(f"          {line}" for line in s["self_check_lines"])]


def _self_check_text(ssim: float | None, nme: float | None, frames: int) -> str:
    if ssim is None or nme is None:
        return f"self-check: no frame scored ({frames} frames)"
    return (f"self-check: face SSIM {ssim:.3f}, render NME {nme:.2f} % over {frames} of the "
            f"build's own frames")


def _model_info(args: argparse.Namespace) -> int:
    from facewire.models.modelfile import load_model, model_summary
    from facewire.report import report
    from facewire.sender.enroll.usage import region_frames_summary

    model = load_model(args.model)
    s = {**model_summary(model), "name": model.info.name,
         "source_video": model.info.source_video, "neutral_frame": model.info.neutral_frame,
         "texture": list(model.texture.shape[:2]), "creator": model.info.creator,
         "source": None if model.info.source is None else model.info.source.as_dict(),
         "coverage": model.coverage,
         "self_check": None if model.self_check is None else model.self_check.as_dict(),
         "region_frames": region_frames_summary(model),
         "learned": None if model.learned is None else model.learned.as_dict()}
    regions = ", ".join(f"{r.name} ({r.layers.shape[0]} layers)" for r in model.regions)
    source = model.info.source
    built = "unknown (a model written before the range was stored)" if source is None else \
        f"{source.text()} ({source.bytes:,} bytes, sha256 {source.sha256[:16]}...)"
    report(s, [f"model:    {args.model}",
               f"person:   {s['name']} (from {s['source_video'] or '-'}, "
               f"neutral frame {s['neutral_frame']})",
               f"built from: {built}",
               f"mesh:     {s['vertices']:,} vertices, {s['triangles']:,} triangles",
               f"texture:  {s['texture'][1]} x {s['texture'][0]}",
               f"regions:  {regions or 'none'}",
               _descriptors_line(s["descriptors"]),
               *_region_frames_lines(s["region_frames"]),
               *_coverage_lines(model.coverage),
               _stored_self_check(model.self_check),
               _learned_line(model.learned),
               f"file:     {s['bytes']:,} bytes, sha256 {s['sha256']}"], args.json)
    return 0


def _descriptors_line(count: int) -> str:
    """``model build/info``'s line on the person's face descriptors (whom senders follow)."""
    if count == 0:
        return ("identity: no face descriptors (a model built before they were stored): "
                "senders cannot hold its person and follow the largest face")
    return (f"identity: {count} face descriptors of the person: senders follow that person "
            f"only")


def _learned_line(learned: Any) -> str:
    """``model info``'s line on the session updates a model includes."""
    if learned is None:
        return "learned:  nothing (no session's model updates)"
    states = ", ".join(f"{u.region} state {u.position}" + (
        "" if u.replaces is None else f" (replacing {u.replaces})") for u in learned.updates)
    return (f"learned:  {len(learned.updates)} model updates of session {learned.log} on "
            f"base {learned.base_sha256[:16]}...: {states}")


def _stored_self_check(check: Any) -> str:
    """``model info``'s self-check line: the stored scores and verdict."""
    if check is None:
        return "self-check: not stored (built with --no-self-check, or before it existed)"
    verdict = f"; POOR, likely cause: {', '.join(check.causes)}" if check.poor else ""
    return _self_check_text(check.ssim, check.render_nme, check.frames) + verdict


def _model_export(args: argparse.Namespace) -> int:
    from facewire.models.gltf import write_glb
    from facewire.models.modelfile import load_model

    model = load_model(args.model)
    mesh = model.mesh
    write_glb(args.output, mesh.vertices, mesh.triangles, mesh.uv, model.texture,
              mesh.vertex_normals())
    print(f"wrote {args.output}: {len(mesh.vertices):,} vertices, {len(mesh.triangles):,} "
          f"triangles, texture {model.texture.shape[1]} x {model.texture.shape[0]}")
    return 0


def _bench_speed(args: argparse.Namespace) -> int:
    from facewire.bench.speed import speed
    from facewire.report import report

    report(*speed(args.model, args.source, progress=_progress,
                  loopback_s=args.loopback_seconds), args.json)
    return 0


def _bench_sync(args: argparse.Namespace) -> int:
    from facewire.bench.speech import losses
    from facewire.bench.sync import sync
    from facewire.report import report

    report(*sync(args.model, args.source, losses(args.loss), _frames(args.frames),
                 progress=_progress, page=args.page, page_seconds=args.page_seconds),
           args.json)
    return 0


def _bench_call(args: argparse.Namespace) -> int:
    from facewire.bench.callcheck import call_check
    from facewire.report import report

    summary, lines = call_check(args.model_a, args.source_a, args.model_b, args.source_b,
                                args.seconds, learn=not args.no_learn, status=lambda line: print(
                                    f"bench call: {line}", file=sys.stderr, flush=True))
    report(summary, lines, args.json)
    return 0 if summary["passed"] else 1


def _bench_speech(args: argparse.Namespace) -> int:
    from facewire.bench.speech import losses, speech_table
    from facewire.report import report

    report(*speech_table(args.source, round(args.voice_kbps * 1000), losses(args.loss)),
           args.json)
    return 0


def _bench_fanout(args: argparse.Namespace) -> int:
    from facewire.bench.fanout import DEFAULT_VIEWERS, fanout
    from facewire.report import report

    report(*fanout(args.model, args.source, args.viewers or DEFAULT_VIEWERS, args.seconds,
                   args.log, status=lambda line: print(f"bench fanout: {line}",
                                                       file=sys.stderr, flush=True),
                   page=not args.no_page),
           args.json)
    return 0


def _encode(args: argparse.Namespace) -> int:
    from facewire.report import report
    from facewire.sender.pipeline import encode_video

    s = encode_video(args.model, args.source, args.output, _frames(args.frames),
                     focal=args.focal, calib=args.calib, progress=_progress,
                     learn=not args.no_learn,
                     warn=lambda text: print(f"facewire encode: {text}", file=sys.stderr),
                     audio=not args.no_audio)
    report(s, [f"log:      {s['log']}",
               f"frames:   {s['frames']} ({s['face_frames']} with a face), {s['packets']} "
               f"packets, {s['payload_kbps']} kbit/s payload at 30 Hz",
               f"flags:    {s['clamped']} frames clamped ({s['clamped_values']} values), "
               f"{s['held']} held, {s['mirrored']} mirrored, {s['tracking_lost']} tracking lost",
               f"voice:    {s['voice_packets']} packets of 20 ms",
               f"learned:  {s['updates']} model updates"
               + (f" ({', '.join(s['update_regions'])})" if s["update_regions"] else ""),
               f"time:     {s['seconds']} s"], args.json)
    return 0


def _bench_quality(args: argparse.Namespace) -> int:
    from facewire.bench.quality import quality
    from facewire.report import report

    report(*quality(args.model, args.source, frames=_frames(args.frames), plot=args.plot,
                    progress=_progress, reference=args.reference,
                    allow_overlap=args.allow_overlap, learn=args.learn), args.json)
    return 0


def _bench_reproductions(args: argparse.Namespace) -> int:
    import tempfile

    from facewire.bench.reproductions import format_table, run_reproductions
    from facewire.report import report

    with tempfile.TemporaryDirectory(prefix="facewire-repro-") as scratch:
        summary = run_reproductions(args.data, args.work or scratch, models=args.models,
                                    only=args.only, limit=args.limit, progress=_progress)
    report(summary, format_table(summary), args.json)
    return 0


def _bench_clips(args: argparse.Namespace) -> int:
    import tempfile

    from facewire.bench.cliptable import format_clip_table, run_clip_table
    from facewire.report import report

    with tempfile.TemporaryDirectory(prefix="facewire-clips-") as scratch:
        summary = run_clip_table(args.data, args.work or scratch, models=args.models,
                                 only=args.only, limit=args.limit, progress=_progress)
    report(summary, format_clip_table(summary), args.json)
    return 0


def _check(_: argparse.Namespace) -> int:
    from facewire.models.infra.egl import check_egl
    from facewire.receiver.speaker import check_sound
    from facewire.sender.enroll.occluders import check_hand_model
    from facewire.sender.enroll.silhouette import check_silhouette_model

    print(check_egl())
    print(check_hand_model())
    print(check_silhouette_model())
    print(check_sound())
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``facewire`` parser: every command of the contract, each with its ``run``."""
    p = argparse.ArgumentParser(
        prog="facewire",
        description="Low-bandwidth face telepresence: a sender tracks a face and sends a "
        "fixed-size packet per frame (< 12 kbit/s at 30 Hz); a receiver morphs and renders "
        "that person's head from it.",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _add_model(sub)
    _add_send_receive(sub)
    _add_encode_replay(sub)
    _add_bench(sub)
    _add_tools(sub)
    return p


def _add_json(parser: argparse.ArgumentParser) -> None:
    """The ``--json`` option of every command that reports."""
    parser.add_argument("--json", action="store_true",
                        help="print a JSON summary as the last line")


def _add_loss(parser: argparse.ArgumentParser) -> None:
    """The ``--loss`` option of the benches that score the speech."""
    parser.add_argument("--loss", default="0,10,30", metavar="L,L,...",
                        help="packet losses to score the speech at, percent (default "
                        "%(default)s)")


def _add_model(sub: Commands) -> None:
    """``model build``, ``model info`` and ``model export``."""
    from facewire.sender.enroll.routine import LEAD_S, RECORD_S

    model = sub.add_parser("model", help="build, inspect and export a person model (.fwm)")
    msub = model.add_subparsers(dest="model_command", metavar="ACTION", required=True)
    m = msub.add_parser("build", help="build a person model from a short video of that person, "
                        "or from one photo, or guided from a camera")
    m.add_argument("video", metavar="VIDEO|PHOTO", nargs="?", help="enrollment video of the "
                   "person making faces, or one photo (.jpg, .jpeg, .png, .bmp, .webp): the "
                   "neutral only")
    m.add_argument("-o", "--output", required=True, help="model file to write (.fwm)")
    m.add_argument("--frames", help="frame range A:B of the video to use (default: all)")
    m.add_argument("--person", metavar="PHOTO|N", help="whom to build the model of when the "
                   "video shows several people: N, the N-th face of the range's first frame "
                   "counted from 0 left to right, or PHOTO, a photo of the person (default: "
                   "the one most present); the senders follow that person only")
    m.add_argument("--from-log", metavar="LOG", help="instead of enrolling: the model a "
                   "session's receivers ended with, the base model (--model) with the model "
                   "updates the session's log holds, so that the next session starts from "
                   "them; the base's sha256 must be the log's")
    m.add_argument("--model", metavar="BASE", help="with --from-log: the model file the "
                   "session started from")
    m.add_argument("--no-self-check", action="store_true",
                   help="skip the self-check (the model rendered at up to 40 of its own "
                   "frames and scored: face SSIM, render NME; about 4 s)")
    guided = m.add_argument_group(
        "guided", "--guided camera:N walks the person through 11 prompts (neutral, brows up, "
        "frown, eyes closed, look left, right, up, down, smile, smile wide, mouth open): each "
        "a lead-in to get ready, then a recorded take; a take that loses the face is asked "
        "again (up to 3 takes). The takes go to a temporary H.264 file, deleted after the "
        "build; each region's states are chosen from the takes of its prompts, the neutral "
        "from the neutral take. A video file may stand in for the camera: the same schedule "
        "runs in the file's own frame time, read as fast as it decodes (in real time with "
        "--view); it must last the whole routine.")
    guided.add_argument("--guided", metavar="CAMERA|VIDEO",
                        help="record the routine from camera:N (or a video file) and build")
    guided.add_argument("--prompt-seconds", type=float, default=RECORD_S,
                        help=f"seconds recorded per prompt (default {RECORD_S:g})")
    guided.add_argument("--lead-seconds", type=float, default=LEAD_S,
                        help=f"seconds to get ready before each take (default {LEAD_S:g})")
    guided.add_argument("--view", action="store_true", help="also show the camera image with "
                        "the prompt on a live page on 127.0.0.1")
    guided.add_argument("--view-port", type=int, default=8765, help="the live page's port "
                        "(default 8765; 0: any free port)")
    _add_json(m)
    m.set_defaults(run=_model_build)
    m = msub.add_parser("info", help="describe a model file")
    m.add_argument("model", help="model file (.fwm)")
    _add_json(m)
    m.set_defaults(run=_model_info)
    m = msub.add_parser("export", help="export a model to glTF 2.0 (.glb)")
    m.add_argument("model", help="model file (.fwm)")
    m.add_argument("-o", "--output", required=True, help="glTF binary to write (.glb)")
    m.set_defaults(run=_model_export)


def _add_insecure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--insecure", action="store_true", help="listen beyond loopback "
                        "without CURVE all the same: unencrypted, and any peer can make the "
                        "process grow without bound")


def _add_send_receive(sub: Commands) -> None:
    """``send`` (camera host) and ``receive`` (render host)."""
    s = sub.add_parser("send", help="track a face and publish packets (camera host)")
    s.add_argument("--model", required=True, help="person model (.fwm)")
    s.add_argument("--source", required=True, help="camera:N or a video file")
    s.add_argument("--bind", default="tcp://127.0.0.1:5555", help="ZeroMQ address to publish on")
    s.add_argument("--record", help="also write the packets to this log (.fwlog)")
    s.add_argument("--rate", type=_rate, default=NOMINAL_HZ,
                   help=f"target frame rate in Hz, {MIN_RATE_HZ:g} to {MAX_RATE_HZ:g}")
    s.add_argument("--loop", action="store_true", help="play a video file over and over, "
                   "until Ctrl-C (long runs, benchmarks)")
    s.add_argument("--curve-dir", help="CURVE key folder (see 'facewire keys generate'): "
                   "encrypt, and admit only the receivers in DIR/authorized")
    _add_insecure(s)
    _add_no_learn(s)
    _add_voice(s, "send")
    _add_json(s)
    s.set_defaults(run=_send)

    r = sub.add_parser("receive", help="receive packets and render the face (render host)")
    r.add_argument("--connect", required=True, help="sender address, e.g. tcp://HOST:5555")
    r.add_argument("--model", help="person model (.fwm); fetched from the sender if omitted")
    out = r.add_mutually_exclusive_group()
    out.add_argument("--out", help="write an H.264 video (.mp4)")
    out.add_argument("--frames", help="write PNG frames to this folder")
    out.add_argument("--view", action="store_true", help="serve a live view (a web page with "
                     "the picture and the statistics) on 127.0.0.1")
    r.add_argument("--view-port", type=int, default=8765, help="the live view's port "
                   "(default 8765; 0: any free port)")
    r.add_argument("--size", help="rendering size WxH (default: the sender camera's; with "
                   "--view or --keep-up at most 960 on its longer side)")
    r.add_argument("--keep-up", action="store_true", help="with --out or --frames: when the "
                   "renderer falls behind the stream, repeat the last frame for a slot already "
                   "overtaken instead of drawing every slot late (a live recording; default: "
                   "every slot drawn, however late)")
    r.add_argument("--idle-timeout", type=float, help="stop after this many seconds without "
                   "packets (default: run until Ctrl-C)")
    r.add_argument("--curve-dir", help="CURVE key folder (see 'facewire keys generate'): "
                   "connect only to the sender whose key is in DIR/authorized")
    _add_voice(r, "receive")
    _add_json(r)
    r.set_defaults(run=_receive)

    c = sub.add_parser("call", help="a call: send this host's face and voice, and receive, "
                       "show and play the other host's", description="One command per host: "
                       "this host's face and voice go out at --bind, the other host's come in "
                       "from --peer and are shown in a live view (its address is printed) "
                       "with their voice. With --curve-dir each side admits only the other's "
                       "key (the folder's authorized/ holds the other's public key alone).")
    c.add_argument("--model", required=True, help="this host's person model (.fwm)")
    c.add_argument("--source", required=True, help="camera:N or a video file (this host)")
    c.add_argument("--peer", required=True, help="the other host's address, tcp://HOST:PORT")
    c.add_argument("--bind", default="tcp://127.0.0.1:5555",
                   help="where this host publishes (default %(default)s; control on PORT+1)")
    c.add_argument("--curve-dir", help="this host's key folder; authorized/ holds the other "
                   "host's public key")
    c.add_argument("--loop", action="store_true", help="play a video file over and over")
    c.add_argument("--no-learn", action="store_true", help="send no model updates (this "
                   "host's unseen appearance is not learned)")
    c.add_argument("--view-port", type=int, default=0, help="the live view's port (default: "
                   "any free one)")
    c.add_argument("--out", help="also write the other side, with their voice, to this .mp4")
    c.add_argument("--idle-timeout", type=float, help="end when the other side has been "
                   "silent this many seconds (default: run until Ctrl-C)")
    _add_insecure(c)
    _add_voice(c, "send")
    c.add_argument("--speaker", metavar="DEVICE", help="play the other's voice on this output "
                   "device (its index or name; default: the default output)")
    _add_json(c)
    c.set_defaults(run=_call)


def _add_voice(parser: argparse.ArgumentParser, command: str) -> None:
    """The voice's options of ``send`` (``--mic``, ``--voice-kbps``) and of ``receive``
    (``--speaker``), and ``--no-audio`` of both."""
    parser.add_argument("--no-audio", action="store_true", help="no voice: the face alone")
    if command == "send":
        parser.add_argument("--mic", metavar="DEVICE", help="take the voice from this "
                            "microphone (mic:N, or a device name; see 'facewire check'); by "
                            "default a video file's own sound track")
        parser.add_argument("--voice-kbps", type=float, default=DEFAULT_BITRATE / 1000,
                            help="Opus's rate, kbit/s, 6 to 24 (default %(default)g: with "
                            "its packet headers 11.6 kbit/s)")
    else:
        parser.add_argument("--speaker", metavar="DEVICE", help="play the voice on this "
                            "output device (its index or name; default: the default output)")


def _add_no_learn(parser: argparse.ArgumentParser) -> None:
    """``--no-learn``: the sender's learning (on by default) turned off."""
    parser.add_argument("--no-learn", action="store_true", help="do not learn: by default "
                        "an appearance the model lacks (a new expression held for a moment) "
                        "is captured as a model update, a new state of that region, for the "
                        "receivers; with --no-learn the model stays as its file")


def _add_encode_replay(sub: Commands) -> None:
    """``encode`` (a video into a packet log) and ``replay`` (a packet log into a video)."""
    e = sub.add_parser("encode", help="run the sender pipeline on a video into a packet log")
    e.add_argument("--model", required=True, help="person model (.fwm)")
    e.add_argument("--source", required=True, help="video file or folder of images")
    e.add_argument("-o", "--output", required=True, help="packet log to write (.fwlog)")
    e.add_argument("--frames", help="frame range A:B of the video to encode (default: all)")
    e.add_argument("--focal", type=float, help="camera focal length in pixels (default: "
                   "estimated from the image width)")
    e.add_argument("--calib", help="camera calibration JSON {fx, fy, cx, cy, width, height}")
    _add_no_learn(e)
    e.add_argument("--no-audio", action="store_true", help="leave the video's sound out of "
                   "the log (by default it is kept as the voice)")
    _add_json(e)
    e.set_defaults(run=_encode)

    rp = sub.add_parser("replay", help="render a recorded packet log to a video",
                        description="Render every frame slot of a packet log (lost packets "
                        "concealed as a live receiver does) with the person's model.")
    rp.add_argument("log", help="packet log (.fwlog)")
    rp.add_argument("--model", required=True, help="person model (.fwm) the log was made with")
    rp.add_argument("--out", required=True, help="H.264 video (.mp4), or a folder for PNG "
                    "frames")
    rp.add_argument("--view", choices=("camera", "front", "three-quarter"), default="camera",
                    help="the sender's camera (default), or a virtual front or three-quarter "
                    "camera")
    rp.add_argument("--size", help="rendering size WxH (default: the sender camera's, "
                    "640x480 for virtual views)")
    rp.add_argument("--side-by-side", metavar="SOURCE", help="the source video, shown left "
                    "of the rendering (input | reconstruction)")
    _add_json(rp)
    rp.set_defaults(run=_replay)


def _add_bench(sub: Commands) -> None:
    """``bench bandwidth``, ``bench speed``, ``bench quality``, ``bench fanout`` and ``bench
    reproductions``."""
    b = sub.add_parser("bench", help="benchmarks: bandwidth, speed, quality, fanout, "
                       "reproductions")
    bsub = b.add_subparsers(dest="bench_command", metavar="BENCH", required=True)
    bb = bsub.add_parser("bandwidth", help="payload, wire and IP bit rates of a packet log "
                         "(exit 1 when its worst 1-s payload is >= 12 kbit/s)")
    bb.add_argument("--log", required=True, help="packet log (.fwlog)")
    _add_json(bb)
    bb.add_argument("--plot", help="write a plot of bits per frame and kbit/s over time (.png)")
    bb.set_defaults(run=_bench_bandwidth)
    bs = bsub.add_parser("speed", help="per-stage timings of sender and receiver")
    bs.add_argument("--model", required=True, help="person model (.fwm)")
    bs.add_argument("--source", required=True, help="video file")
    bs.add_argument("--loopback-seconds", type=float, default=30.0, metavar="S",
                    help="seconds of the live run of a real sender process and a receiver on "
                    "127.0.0.1 that measures the end-to-end latency and the memory growth "
                    "(default 30; 0 skips it)")
    _add_json(bs)
    bs.set_defaults(run=_bench_speed)
    bq = bsub.add_parser("quality", help="geometry and appearance fidelity on a real video")
    bq.add_argument("--model", required=True, help="person model (.fwm)")
    bq.add_argument("--source", required=True, help="video file")
    bq.add_argument("--frames", help="frame range A:B to measure on")
    bq.add_argument("--reference", help="OpenFace CSV of the same video, for Q agreement")
    bq.add_argument("--allow-overlap", action="store_true",
                    help="score frames the model was built from (refused by default; the "
                    "report then says how many)")
    bq.add_argument("--learn", action="store_true",
                    help="let the sender learn unseen appearance during the run, as send and "
                    "encode do (off: the model file is scored as it was built)")
    _add_json(bq)
    bq.add_argument("--plot", help="write a plot of fidelity over time (.png)")
    bq.set_defaults(run=_bench_quality)
    bf = bsub.add_parser("fanout", help="one sender through a relay to N WebSocket viewers (via "
                         "facewire web) and N ZeroMQ subscribers: delivery, latency, CPU")
    bf.add_argument("--model", required=True, help="person model (.fwm)")
    fsrc = bf.add_mutually_exclusive_group(required=True)
    fsrc.add_argument("--source", help="video file, encoded with the model into the stream")
    fsrc.add_argument("--log", help="packet log (.fwlog) of the model, sent instead")
    bf.add_argument("--viewers", type=int, action="append", metavar="N",
                    help="viewers of each kind in a run (repeatable; default 10, 100, 1000)")
    bf.add_argument("--seconds", type=float, default=10.0, metavar="S",
                    help="each run's measured window (default 10)")
    bf.add_argument("--no-page", action="store_true",
                    help="skip the page run (the gateway's page in headless Chromium: its "
                         "frame rate at 640x480; made by default, skipped without Chromium)")
    _add_json(bf)
    bf.set_defaults(run=_bench_fanout)
    br = bsub.add_parser("reproductions", help="issues 16's and 24's reproductions (occluded "
                         "mouth, no open mouth, fast head motion, a real hand on the mouth): "
                         "models built and scored, one table")
    br.add_argument("--data", required=True, help="the shared data folder (holds video/)")
    br.add_argument("--work", help="folder to keep the models and the occluded copy in "
                    "(default: a temporary one)")
    br.add_argument("--models", help="folder of models KEY.fwm to score instead of building "
                    "(occluded, closed, motion, hand)")
    br.add_argument("--only", action="append", metavar="KEY",
                    help="run this reproduction only (repeatable)")
    br.add_argument("--limit", type=int, metavar="N",
                    help="score only the first N held-out frames of each")
    _add_json(br)
    br.set_defaults(run=_bench_reproductions)
    bsy = bsub.add_parser("sync", help="face and voice sent and received live on loopback: "
                          "their playout skew, the lip sync in the received video, and the "
                          "voice's speech quality (PESQ-WB) at packet losses")
    bsy.add_argument("--model", required=True, help="person model (.fwm) of the clip's person")
    bsy.add_argument("--source", required=True, help="a talking video with its sound track")
    bsy.add_argument("--frames", help="frame range A:B of the video to send (default: all)")
    _add_loss(bsy)
    bsy.add_argument("--page", action="store_true", help="also play the clip, looped, on the "
                     "gateway's page in headless Chromium and measure the page's own skew")
    bsy.add_argument("--page-seconds", type=float, default=10.0, metavar="S",
                     help="the page's measuring window (default %(default)s)")
    _add_json(bsy)
    bsy.set_defaults(run=_bench_sync)
    bca = bsub.add_parser("call", help="a call on one machine: two 'facewire call' processes, "
                          "each sending a clip looped, checked for loss, memory (RSS every "
                          "10 s) and sync over the whole call")
    bca.add_argument("--model-a", required=True, help="side A's person model (.fwm)")
    bca.add_argument("--source-a", required=True, help="side A's video (looped)")
    bca.add_argument("--model-b", required=True, help="side B's person model (.fwm)")
    bca.add_argument("--source-b", required=True, help="side B's video (looped)")
    bca.add_argument("--seconds", type=float, default=600.0,
                     help="the call's length (default %(default)s)")
    bca.add_argument("--no-learn", action="store_true", help="both sides send no model "
                     "updates (memory then holds no learned versions)")
    _add_json(bca)
    bca.set_defaults(run=_bench_call)
    bsp = bsub.add_parser("speech", help="the voice's speech quality (PESQ-WB) through its "
                          "real packets and jitter buffer at packet losses, against the source "
                          "and the codec alone, one line per clip (no face, no model)")
    bsp.add_argument("--source", required=True, action="append", metavar="V",
                     help="a video or sound file with a sound track (repeatable)")
    bsp.add_argument("--voice-kbps", type=float, default=DEFAULT_BITRATE / 1000,
                     help="Opus's rate, kbit/s, 6 to 24 (default %(default)g)")
    _add_loss(bsp)
    _add_json(bsp)
    bsp.set_defaults(run=_bench_speech)
    bc = bsub.add_parser("clips", help="every single-person shared clip: a model from its first "
                         "40 %%, scored on the rest beside x264 at its floor, one table")
    bc.add_argument("--data", required=True, help="the shared data folder (holds video/)")
    bc.add_argument("--work", help="folder to keep the models in (default: a temporary one)")
    bc.add_argument("--models", help="folder of models CLIP.fwm (the clip's name without its "
                    "suffix) to score instead of building")
    bc.add_argument("--only", action="append", metavar="CLIP",
                    help="run this clip only (its file name; repeatable)")
    bc.add_argument("--limit", type=int, metavar="N",
                    help="score only the first N held-out frames of each")
    _add_json(bc)
    bc.set_defaults(run=_bench_clips)


def _add_tools(sub: Commands) -> None:
    """``inspect``, ``relay``, ``web``, ``demo``, ``keys generate`` and ``check``."""
    i = sub.add_parser("inspect", help="summarise a packet log; optionally dump it as CSV")
    i.add_argument("log", help="packet log (.fwlog)")
    i.add_argument("--csv", help="write every frame's decoded fields to this CSV")
    _add_json(i)
    i.set_defaults(run=_inspect)

    x = sub.add_parser("relay", help="fan packets from senders out to receivers (ZeroMQ proxy)")
    x.add_argument("--in", dest="inp", required=True, help="address senders publish to")
    x.add_argument("--out", required=True, help="address receivers connect to")
    x.add_argument("--curve-in", help="client key folder for the link to the sender")
    x.add_argument("--curve-out", help="server key folder for the receivers' side")
    _add_insecure(x)
    _add_json(x)
    x.set_defaults(run=_relay)

    w = sub.add_parser("web", help="serve the stream to web browsers: a page that renders "
                       "the face itself (WebGL2), fed the packets over a WebSocket")
    w.add_argument("--connect", required=True, help="sender or relay address, e.g. "
                   "tcp://HOST:5555")
    w.add_argument("--curve-dir", help="CURVE key folder (see 'facewire keys generate'): "
                   "connect only to the sender whose key is in DIR/authorized")
    w.add_argument("--http", metavar="HOST:PORT",
                   help="where to serve the page and the WebSocket (default 127.0.0.1:8080; "
                   "port 0: any free one)")
    w.add_argument("--token-file", metavar="FILE", help="the token every request carries "
                   "(?token=, in the page's URL) is the first line of FILE, made with a new "
                   "token if it does not exist (default: $FACEWIRE_TOKEN, or a new token for "
                   "this run, told in a private file)")
    w.add_argument("--token", help=argparse.SUPPRESS)  # shown by ps: kept, with a warning
    w.add_argument("--allow-remote", action="store_true", help="serve on an address other "
                   "than loopback (plain HTTP: unencrypted)")
    w.add_argument("--host", action="append", metavar="NAME", help="with --allow-remote: a "
                   "DNS name the page is opened by (repeatable); requests naming another "
                   "name are refused (DNS rebinding)")
    _add_json(w)
    w.set_defaults(run=_web)

    d = sub.add_parser("demo", help="the embedded default: build, perform, send, receive, render")
    d.add_argument("--source", help="a real video of one person instead of the embedded "
                   "performance: its first 4 s build the model, the rest is streamed")
    d.add_argument("--out", default="facewire-demo", help="output folder (default: "
                   "facewire-demo)")
    d.add_argument("--seconds", type=float, help="stream at most this many seconds")
    _add_json(d)
    d.set_defaults(run=_demo)

    k = sub.add_parser("keys", help="CURVE key management")
    ksub = k.add_subparsers(dest="keys_command", metavar="ACTION", required=True)
    kg = ksub.add_parser("generate", help="make a CURVE key pair in DIR")
    kg.add_argument("dir", help="key folder (created if missing)")
    kg.add_argument("--name", default="id", help="key pair file name (default: id)")
    kg.set_defaults(run=_keys_generate)

    c = sub.add_parser("check", help="check the system: headless OpenGL (EGL) and Mesa, the "
                       "enrollment's hand and person models (mediapipe), and the sound")
    c.set_defaults(run=_check)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except USER_ERRORS as exc:
        print(f"facewire: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("facewire: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
