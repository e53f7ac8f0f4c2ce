"""How torchfra runs: ranks of a ``torch.distributed`` group (:mod:`.distributed`) and the host
process's memory allocator (:mod:`.allocator`). Imports nothing else of torchfra."""
