"""triswarm.sitl."""

from triswarm.protocol import jit as _jit

_jit.cache_on_disk()  # protocol/'s compiled code kept across runs, in numba's cache (files: protocol/ writes none itself)
