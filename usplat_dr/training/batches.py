"""The training stream: batches over epochs with a position a resumed run replays to."""

from torch.utils.data import DataLoader

from usplat_dr.config import ConfigError


class Batches:
    """An endless stream of batches over epochs, with a position (epoch, batches taken in the
    epoch) that a resumed run replays to: the same batches in the same order."""

    def __init__(self, dataset, batch_size: int, num_workers: int):
        self.dataset = dataset
        self.loader = DataLoader(dataset, batch_size=batch_size, num_workers=num_workers,
                                 persistent_workers=False)
        self.epoch, self.taken = 0, 0
        self._it = None

    def state(self) -> dict:
        """The position in the stream, for a checkpoint."""
        return {"epoch": self.epoch, "taken": self.taken}

    def restore(self, state: dict) -> None:
        """Go back to ``state()``'s position (the same batches follow). A ``ConfigError``
        when the epoch now has fewer batches than the position (the data changed)."""
        self.epoch, self.taken = state["epoch"], 0
        self.dataset.set_epoch(self.epoch)
        self._it = iter(self.loader)
        for _ in range(state["taken"]):  # replay (decodes the skipped batches once)
            try:
                next(self._it)
            except StopIteration:
                raise ConfigError(
                    f"its data position is batch {state['taken']} of epoch {self.epoch}, but "
                    f"the training set now gives {self.taken} batch(es) an epoch (the data "
                    f"under dataset.roots changed): put the data back, or start a new run in "
                    f"another output_dir") from None
            self.taken += 1

    def next(self) -> dict:
        """The next batch, starting a new epoch when one ends."""
        for _ in range(2):
            if self._it is None:
                self.dataset.set_epoch(self.epoch)
                self._it = iter(self.loader)
            try:
                batch = next(self._it)
                self.taken += 1
                return batch
            except StopIteration:
                self._it, self.epoch, self.taken = None, self.epoch + 1, 0
        raise ConfigError("the training set yields no examples (see the dataset summary "
                          "above: too few frames for the view sampler, or every scene skipped)")
