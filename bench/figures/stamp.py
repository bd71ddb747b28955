"""Stamp a picture the docs show with what made it: a grey footer line and PNG text metadata.

The footer says the command that regenerates the picture, the data it read and the date; the PNG's text chunks
(``Title``, ``Description``, ``Source``, ``Software``, ``Creation Time``, ``geocd:command``, ``geocd:data``,
``geocd:commit``) say the same for a program. Stamping is done once per fresh picture (a stamped file carries
``geocd:stamped``), so re-stamping an untouched picture does nothing.
"""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path

import matplotlib
from PIL import Image, ImageDraw, ImageFont
from PIL.PngImagePlugin import PngInfo

#: the footer's height in pixels and its text size
FOOTER_PX = 18
FONT_PX = 11
#: grey of the footer text
FOOTER_GREY = (110, 110, 110)


def _font() -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    path = Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans.ttf"
    try:
        return ImageFont.truetype(str(path), FONT_PX)
    except OSError:  # no TrueType font: PIL's own bitmap font
        return ImageFont.load_default()


def is_stamped(path: os.PathLike | str) -> bool:
    """True when the PNG already carries a stamp."""
    with Image.open(path) as im:
        return "geocd:stamped" in getattr(im, "text", {})


def footer_text(command: str, data: str, date: str) -> str:
    """The footer line: command · data · date."""
    return f"made by: {command}  ·  data: {data}  ·  {date}"


def stamp(
    path: os.PathLike | str,
    *,
    command: str,
    data: str,
    shows: str = "",
    commit: str = "",
    date: str | None = None,
) -> bool:
    """Add the footer and the metadata to the PNG at ``path`` (in place); False when it was stamped already.

    Parameters
    ----------
    path : a PNG file
    command : the command that regenerates it (e.g. ``python -m bench.figures --only NAME``)
    data : the data it read (folders of ``../shared/data``, or the committed scene)
    shows : what the picture shows (its caption; the PNG's ``Description``)
    commit : the git commit of the code that made it
    date : ISO date (default: today, UTC)
    """
    p = Path(path)
    date = date or _dt.datetime.now(_dt.timezone.utc).date().isoformat()
    with Image.open(p) as im:
        if "geocd:stamped" in getattr(im, "text", {}):
            return False
        im.load()
        mode = "RGBA" if im.mode in ("RGBA", "LA", "P") else "RGB"
        src = im.convert(mode)
    w, h = src.size
    out = Image.new(mode, (w, h + FOOTER_PX), (255, 255, 255, 255) if mode == "RGBA" else (255, 255, 255))
    out.paste(src, (0, 0))
    draw = ImageDraw.Draw(out)
    text = footer_text(command, data, date)
    font = _font()
    while len(text) > 20 and draw.textlength(text, font=font) > w - 8:  # a narrow picture: shorten the line
        text = text[: int(len(text) * 0.9) - 1] + "…"
    draw.text((4, h + (FOOTER_PX - FONT_PX) // 2 - 1), text, fill=FOOTER_GREY, font=font)
    info = PngInfo()
    meta = {
        "Title": p.name,
        "Description": shows,
        "Source": command,
        "Software": "geocd bench/figures",
        "Creation Time": date,
        "geocd:command": command,
        "geocd:data": data,
        "geocd:commit": commit,
        "geocd:stamped": "1",
    }
    for k, v in meta.items():
        info.add_text(k, str(v))
    tmp = p.with_name(f".{p.name}.part")
    out.save(tmp, "PNG", pnginfo=info, optimize=True)
    os.replace(tmp, p)
    return True
