"""Test-suite settings.

The fits in these tests work on tiny tensors, where torch's intra-op thread pool costs more
than it gives (and slows everything down badly when the machine is busy): run single-threaded.
"""

import torch

torch.set_num_threads(1)
