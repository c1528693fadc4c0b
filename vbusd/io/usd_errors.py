"""USD's error messages as one clean line (shared by the stage reader and the crate probe)."""

from __future__ import annotations

import re
from typing import Optional

__all__ = ["one_line", "error_text", "tf_message"]

_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f-\x9f]")


def one_line(text: str, limit: int = 600) -> str:
    """``text`` as one printable line: whitespace runs collapsed, control bytes escaped, cut."""
    text = _CONTROL.sub(lambda m: f"\\x{ord(m.group(0)):02x}", " ".join(str(text).split()))
    return text if len(text) <= limit else text[:limit - 3] + "..."


def error_text(error: BaseException) -> Optional[str]:
    try:
        return str(error)
    except UnicodeDecodeError:
        return None


def tf_message(error: BaseException) -> str:
    """The human part of a ``Tf.ErrorException`` (or any pxr error), as one clean line.

    USD formats its errors as ``Error in 'Sdf_...' at line N in file X : 'message'``; one exception
    can hold several, joined here with "; ". When USD echoes bytes of the input that are not
    UTF-8, ``str(error)`` itself fails; the message then says so and names USD's function, and
    callers that know the file add the byte offset (:func:`first_non_utf8`).
    """
    text = error_text(error)
    if text is None:
        functions = []
        for item in getattr(error, "args", ()):
            function = getattr(item, "sourceFunction", "") or ""
            functions.append(function.rsplit("::", 2)[-2] if "::" in function else function)
        where = f" (in {', '.join(f for f in functions if f)})" if any(functions) else ""
        return f"USD reported an error whose text is not valid UTF-8{where}"
    text = text.strip()
    found = re.findall(r"Error in '[^']*' at line \d+ in file [^:]*? : '(.*?)'\s*(?=Error in '|$)",
                       text, flags=re.S)
    if not found:
        match = re.search(r" : '(.*)'\s*$", text, flags=re.S)
        found = [match.group(1)] if match else [text]
    return one_line("; ".join(dict.fromkeys(" ".join(m.split()) for m in found)))
