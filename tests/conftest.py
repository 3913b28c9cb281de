"""Suite-wide settings."""

import torch

# One torch thread in the test process, as the learner uses by default: with two threads on a
# 2-core box that also runs the test's learner/worker processes (or a noisy neighbour), OpenMP's
# spinning threads wait on each other; an in-process training test measured 8 s with one thread
# and 180 s with two while another run shared the box. Results do not depend on it.
torch.set_num_threads(1)
