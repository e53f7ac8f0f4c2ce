"""The diagnosis's progress bar: FE solves done and expected, elapsed time and an estimate of the time left."""
from __future__ import annotations


class _Progress:
    """A labelled bar counting FE solves (each ~10-20 s at resolution 1) with elapsed time and an
    estimate of the time left: the plan (solves still expected) is set as each phase starts, from the
    typical counts (a Gauss-Newton fit takes about ``FIT_SOLVES`` solves); tqdm's rate turns it into
    time."""

    FIT_SOLVES = 4

    def __init__(self, enabled: bool):
        self.enabled, self.bar = enabled, None

    def phase(self, label: str, expected: int | None = None):
        """Start a phase; ``expected``: solves still expected in the whole diagnosis from here on."""
        if not self.enabled:
            return
        from tqdm.auto import tqdm

        if self.bar is None:
            self.bar = tqdm(desc=label, unit="solve", total=expected,
                            bar_format="{desc}{n}/~{total} FE solves [{elapsed} elapsed, ~{remaining} left]")
        self.bar.set_description(label)
        if expected is not None:
            self.bar.total = self.bar.n + expected
            self.bar.refresh()

    def tick(self, n=1):
        if self.bar is not None:
            self.bar.update(1)
            if self.bar.total is not None and self.bar.n >= self.bar.total:
                self.bar.total = self.bar.n + 1  # a fit that takes longer than typical

    def close(self):
        if self.bar is not None:
            self.bar.close()

