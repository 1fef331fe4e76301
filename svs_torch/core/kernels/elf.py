"""Whether a cached shared library is whole, before the dynamic loader maps it.

A library cut short (a disk that filled while a cache folder was copied, an interrupted sync of a home folder)
can still pass the dynamic loader's checks, which read only its headers: its segments are then mapped past the
end of the file, and the first call into them ends the process with SIGBUS, without a word (an audit: a cached
``block_match`` library truncated to 4 096 or 60 000 of its 94 336 bytes; ``estimate`` exited 135, printing
nothing). The loader's own builds are renamed into place only when complete, so this is only ever another
tool's damage. Only ELF files are read (Linux and the BSDs); other formats are left to their loader.
"""

from __future__ import annotations

import struct
from pathlib import Path

__all__ = ["cut_short"]

_MAGIC = b"\x7fELF"
#: (header layout after e_ident, program header layout, where p_offset and p_filesz are in it) by ELF class.
_LAYOUTS = {1: ("HHIIIIIHHHHHH", "IIIIIIII", 1, 4), 2: ("HHIQQQIHHHHHH", "IIQQQQQQ", 2, 5)}
_PT_LOAD = 1


def cut_short(path: Path) -> str | None:
    """Why the ELF file at ``path`` is not whole (its header, program headers, a loaded segment or its section
    headers end past the file's end), or None when it is whole or not an ELF file."""
    data = path.read_bytes()
    if len(data) < 16:
        return f"it is cut short ({len(data)} bytes)" if _MAGIC.startswith(data[:4]) else None
    if data[:4] != _MAGIC or data[4] not in _LAYOUTS or data[5] not in (1, 2):
        return None
    header, program, offset_at, size_at = _LAYOUTS[data[4]]
    order = "<" if data[5] == 1 else ">"
    header_size = 16 + struct.calcsize(order + header)
    if len(data) < header_size:
        return f"it is cut short ({len(data)} bytes, less than its ELF header)"
    fields = struct.unpack_from(order + header, data, 16)
    phoff, shoff = fields[4], fields[5]
    phentsize, phnum, shentsize, shnum = fields[8], fields[9], fields[10], fields[11]
    ends = [phoff + phentsize * phnum, shoff + shentsize * shnum if shnum else 0]
    if ends[0] <= len(data) and phentsize >= struct.calcsize(order + program):
        for index in range(phnum):
            entry = struct.unpack_from(order + program, data, phoff + index * phentsize)
            if entry[0] == _PT_LOAD:
                ends.append(entry[offset_at] + entry[size_at])
    needed = max(ends)
    if needed > len(data):
        return f"it is cut short ({len(data)} bytes, where its ELF headers describe {needed})"
    return None
