"""Test-wide settings. The networks under test are tiny: one torch thread is as fast as two on an idle
machine and many times faster on a loaded one (thread oversubscription), so tests use one."""
import torch

torch.set_num_threads(1)
