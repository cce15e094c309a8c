import os

# Two processes with two torch threads each slow this 2-core machine down more than tenfold.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

torch.set_num_threads(int(os.environ.get("SP_TEST_THREADS", "1")))
