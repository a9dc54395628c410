"""Padding moved beside the graph it pads (`eqsmooth/factors/_padding.py`);
its public names stay importable from `eqsmooth.solve`."""

from ..factors._padding import (
    pad_graph as pad_graph,
    PaddedGraph as PaddedGraph,
    padding_size as padding_size,
    power_of_two as power_of_two,
)
