"""What a controller changes at run time without a rebuild: the obstacle regions (and the margins they are
planned around with), the keep-in flags and the run-time settings.

`RuntimeChanges` is a mixin of NmpcController (core/sample/controller.py), which builds the NLPs and holds
`settings`, `model`, `nlp`, `tiered`, `memory` and the region records used here.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..config.settings import RUNTIME_FIELDS, ControllerSettings
from ..errors import ConfigError
from ..problem.regions import Region, RegionError


class RuntimeChanges:
    """Run-time changes of NmpcController: nothing here builds a solver."""

    @property
    def regions(self) -> tuple[Region, ...]:
        """The obstacle regions as set (the plan avoids them inflated by `region_margin`)."""
        return self._given

    @property
    def planned_regions(self) -> tuple[Region, ...]:
        """The obstacle regions the plan avoids: as set, inflated by `region_margin` and the mismatch margin."""
        return self._regions

    def set_regions(self, regions: Sequence[Region], margin: float | None = None) -> None:
        """Replace the obstacle regions, planned around inflated by `margin` (default planning_margin: region_margin
        and the robot's body) plus the mismatch margin; RegionError if they do not fit the slots, nothing changes
        then."""
        mismatch = self.memory.mismatch.margin
        m = (self.settings.planning_margin if margin is None else margin) + mismatch
        given = tuple(regions)
        planned = tuple(r.inflated(m) if isinstance(r, Region) else r for r in given)
        slots = self.nlp.slot_layout.pack(list(planned), self.nlp.output_frame_available, predict=False)
        self._given, self._regions, self._slots, self.mismatch_margin = given, planned, slots, mismatch
        self.tiered.set_regions(self._regions)
        self._moving = any(r.moving for r in self._regions)

    def slot_values(self, time: float | None = None) -> np.ndarray:
        """The obstacle slot parameters of a sample whose x(0) is valid at `time` (s): with `predict_obstacles`
        on, moving regions placed where they are then and predicted stage by stage (time None: each pose valid
        at x(0)); off, each stays where it was at its stamp. Static regions only: the slots packed once per set."""
        if self._moving and self.settings.predict_obstacles:
            return self.nlp.slot_layout.pack(list(self._regions), self.nlp.output_frame_available, time)
        return self._slots

    def given_slot_values(self, time: float | None = None) -> np.ndarray:
        """The slot parameters of the regions as given, without the margins (`slot_values` plans around them
        inflated), grown by the robot's body only (what the point the plane tracks must avoid): packed on request,
        to tell whether a region itself or only its margin is unavoidable."""
        body = self.settings.body_radius
        real = [r.inflated(body) if body > 0 and isinstance(r, Region) else r for r in self._given]
        return self.nlp.slot_layout.pack(real, self.nlp.output_frame_available, time,
                                         predict=self._moving and self.settings.predict_obstacles)

    @property
    def keep_in_active(self) -> np.ndarray:
        return self._keep_in_active  # one flag per keep_in entry (1: penalised), see set_keep_in_active

    def set_keep_in_active(self, active: Sequence[bool]) -> None:
        """Switch the configured algebraic regions on or off (one flag per `keep_in` entry)."""
        flags = np.asarray(active, dtype=float).ravel()
        if flags.size != self.nlp.layout.n_keep_in:
            raise ConfigError(f"expected {self.nlp.layout.n_keep_in} keep-in flags, got {flags.size}")
        self._keep_in_active = flags

    def checked_settings(self, **changes: float | Sequence[float]) -> ControllerSettings:
        """The settings with run-time fields changed, validated but not applied (ConfigError says why)."""
        structural = sorted(set(changes) - RUNTIME_FIELDS)
        if structural:
            raise ConfigError(f"changing {', '.join(structural)} needs a new controller (NLP rebuild)")
        new = self.settings.replace(**changes)
        for name, size in (("state_weights", self.model.n), ("input_weights", self.model.m)):
            if len(getattr(new, name)) != size:
                raise ConfigError(f"{name} needs {size} values, got {len(getattr(new, name))}")
        return new

    def update_settings(self, **changes: float | Sequence[float]) -> None:
        """Change run-time fields (mu, kappa, weights, predict_obstacles, ...) for the next step; nothing is rebuilt."""
        new = self.checked_settings(**changes)
        if new.planning_margin != self.settings.planning_margin:
            self.set_regions(self._given, new.planning_margin)  # RegionError: nothing changes
        self.settings = new

    def _track_mismatch(self, x: np.ndarray, time: float | None) -> None:
        """Measure the last sample's one-step prediction error at x [n]; re-pack the regions when the mismatch
        margin changed (a region that cannot take it keeps the old one)."""
        mismatch = self.memory.mismatch
        outputs = any(r.frame == "output" for r in self._given if isinstance(r, Region))
        mismatch.measure(x, time, self.latency.advance, self.model, self.settings, outputs)
        mismatch.update(self.settings)
        if mismatch.margin != self.mismatch_margin:
            try:
                self.set_regions(self._given)
            except RegionError:
                mismatch.margin = self.mismatch_margin

