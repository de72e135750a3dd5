"""The estimator firmware's serial wire format, `needlecue-wire/1` (docs/live.md).

115200 baud, 8N1, ASCII lines ending in `\\n` (`\\r\\n` accepted). After a reset the firmware prints
one banner line saying what it is; then one line per sample at 30 Hz:

    #needlecue-wire/1 unit=est-sim-101 channels=fsr1,fsr2,fsr3 adc_bits=10 vref_v=5.0 rate_hz=30
    123456,117,95,117

`millis` is the board's `millis()` (an unsigned 32-bit count that wraps after 49.7 days), then one
ADC count per channel. Lines starting with `#` are comments; the banner is the one that starts with
`#needlecue-wire/1`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

WIRE = "needlecue-wire/1"
BAUD = 115200
RATE_HZ = 30.0
MAX_LINE = 256  # bytes: a longer run without a line break is garbage (a wrong baud rate, noise)
MILLIS_WRAP = 2**32
MAX_ADC_BITS = 24


@dataclass(frozen=True)
class Banner:
    """What the firmware says it is. Fields it leaves out are None."""

    unit_id: str | None = None
    channels: tuple[str, ...] | None = None
    adc_bits: int | None = None
    vref_v: float | None = None
    rate_hz: float | None = None


@dataclass(frozen=True)
class Sample:
    """One data line: the board's millis and one ADC count per channel."""

    millis: int
    counts: tuple[int, ...]


def format_banner(banner: Banner) -> bytes:
    """The banner line the firmware prints after a reset."""
    parts = [f"#{WIRE}"]
    if banner.unit_id:
        parts.append(f"unit={banner.unit_id}")
    if banner.channels:
        parts.append("channels=" + ",".join(banner.channels))
    if banner.adc_bits is not None:
        parts.append(f"adc_bits={banner.adc_bits}")
    if banner.vref_v is not None:
        parts.append(f"vref_v={banner.vref_v:g}")
    if banner.rate_hz is not None:
        parts.append(f"rate_hz={banner.rate_hz:g}")
    return (" ".join(parts) + "\n").encode("ascii")


def format_sample(sample: Sample) -> bytes:
    """One data line as the firmware sends it."""
    return (",".join(str(v) for v in (sample.millis % MILLIS_WRAP, *sample.counts)) + "\n").encode("ascii")


def parse_banner(text: str) -> Banner:
    """The banner's fields; raises ValueError naming a field it cannot read."""
    words = text.strip().lstrip("#").split()
    if not words or words[0] != WIRE:
        raise ValueError(f"not a {WIRE} banner: {text.strip()[:60]!r}")
    fields = dict(w.split("=", 1) for w in words[1:] if "=" in w)
    try:
        banner = Banner(
            unit_id=fields.get("unit") or None,
            channels=tuple(fields["channels"].split(",")) if fields.get("channels") else None,
            adc_bits=int(fields["adc_bits"]) if "adc_bits" in fields else None,
            vref_v=float(fields["vref_v"]) if "vref_v" in fields else None,
            rate_hz=float(fields["rate_hz"]) if "rate_hz" in fields else None,
        )
    except ValueError as e:
        raise ValueError(f"banner field unreadable ({e}): {text.strip()[:80]!r}") from e
    # a garbled or hostile banner must not set a setting that breaks the conversion
    if banner.adc_bits is not None and not 1 <= banner.adc_bits <= MAX_ADC_BITS:
        raise ValueError(f"banner adc_bits={banner.adc_bits} outside 1..{MAX_ADC_BITS}")
    for name in ("vref_v", "rate_hz"):
        value = getattr(banner, name)
        if value is not None and not (math.isfinite(value) and 0 < value <= 1e6):
            raise ValueError(f"banner {name}={value} is not a positive finite number")
    return banner


def parse_line(raw: bytes, n_channels: int, adc_max: int) -> Sample | Banner | str | None:
    """One line off the wire: a Sample, the Banner, None for a comment or a blank line, or a string
    saying why the line is garbage (the caller counts and shows it, and goes on)."""
    if len(raw) > MAX_LINE:
        return f"a line of {len(raw)} bytes (longest valid: {MAX_LINE})"
    try:
        text = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        return "bytes that are not ASCII"
    if not text:
        return None
    if text.startswith("#"):
        if text[1:].startswith(WIRE):
            try:
                return parse_banner(text)
            except ValueError as e:
                return str(e)
        return None
    fields = text.split(",")
    if len(fields) != 1 + n_channels:
        return f"{len(fields)} fields, expected millis and {n_channels} counts"
    try:
        millis, *counts = (int(f) for f in fields)
    except ValueError:
        return f"a field that is not an integer: {text[:40]!r}"
    if not 0 <= millis < MILLIS_WRAP:
        return f"millis {millis} outside 0..2^32-1"
    if any(not 0 <= c <= adc_max for c in counts):
        return f"a count outside 0..{adc_max}: {counts}"
    return Sample(millis, tuple(counts))
