"""The ports of the bin search's Diagrams as tables and pictures, read from the code (the docs
site's concepts page shows them; `docs/hooks.py` calls `concept_diagrams`, `ports_table` and
`graphviz_svg`).

`concept_diagrams()` builds the Diagrams a bin search is made of: the simulated station
(FloatingGripperBin), its controller, the two wired together, and the hardware twin of the YuMi
station with a controller that reads only the camera images. `ports_table(system)` lists every
exported input and output port of a System with its type; `graphviz_svg(system)` draws it with
Graphviz's `dot` (None when `dot` is not installed).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass

from pydrake.lcm import DrakeLcm
from pydrake.systems.framework import DiagramBuilder, PortDataType

from ms_drake.perception.occupancy import TargetBox
from ms_drake.policies.bin_search import BinSearchConfig, MakeBinSearchController, SimulationInfo, connect_controller
from ms_drake.scenario import load_scenario
from ms_drake.station import MakeStation

#: The hardware example's target: a 4.5 x 4.5 x 0.5 cm box (Table 8.2's target).
HARDWARE_TARGET = TargetBox(0.045, 0.045, 0.005)


@dataclass(frozen=True)
class PortRow:
    """One exported port: "input" or "output", its name and its value type."""

    direction: str
    name: str
    type: str


def _cpp_type(name: str) -> str:
    """A pydrake template class name as text: Value𝓣list𝓣RigidTransform𝓤𝓤 -> list[RigidTransform],
    Value𝓣Image𝓣PixelType𝓹kRgba8U𝓤𝓤 -> ImageRgba8U."""
    text = name.replace("𝓣", "[").replace("𝓤", "]").replace("𝓹", ".")
    text = re.sub(r"Image\[PixelType\.k(\w+)\]", r"Image\1", text)
    return text.removeprefix("Value[").removesuffix("]") if text.startswith("Value[") else text


def port_type(port) -> str:
    """A port's value type: "vector[n]" for a vector port, else the type of the value it holds
    (a Python value's module-qualified class, a Drake value's C++ type)."""
    if port.get_data_type() == PortDataType.kVectorValued:
        return f"vector[{port.size()}]"
    value = port.Allocate()
    kind = type(value).__name__
    if kind != "Value𝓣object𝓤":
        return _cpp_type(kind)
    held = type(value.get_value())
    module = held.__module__.removeprefix("ms_drake.")
    return held.__qualname__ if module == "builtins" else f"{module}.{held.__qualname__}"


def port_rows(system) -> list[PortRow]:
    """Every exported input port, then every output port, of `system` in port order."""
    rows = [PortRow("input", system.get_input_port(i).get_name(), port_type(system.get_input_port(i)))
            for i in range(system.num_input_ports())]
    rows += [PortRow("output", system.get_output_port(i).get_name(), port_type(system.get_output_port(i)))
             for i in range(system.num_output_ports())]
    return rows


def ports_table(system) -> str:
    """The ports of `system` as a markdown table: direction, name, type."""
    lines = ["| direction | port | type |", "|---|---|---|"]
    lines += [f"| {r.direction} | `{r.name}` | `{r.type}` |" for r in port_rows(system)]
    return "\n".join(lines) + "\n"


def graphviz_svg(system, max_depth: int = 1, dot: str | None = None) -> str | None:
    """`system`'s Graphviz picture as SVG text, drawn by `dot` (default: the one on PATH); None
    when Graphviz is not installed."""
    exe = dot or shutil.which("dot")
    if exe is None:
        return None
    out = subprocess.run([exe, "-Tsvg"], input=system.GetGraphvizString(max_depth=max_depth), text=True,
                         capture_output=True, check=True, timeout=120)
    svg = out.stdout
    return svg[svg.index("<svg"):] if "<svg" in svg else svg  # no XML prologue: the SVG goes in a page as is


def concept_diagrams() -> dict:
    """The Diagrams of the concepts page by name:

    bin_station: the simulated bin station with the floating gripper (FloatingGripperBin);
    bin_controller: the bin-search controller on it, with the simulation's ports (BinSearchConfig's
    defaults: X-Ray, ground-truth masks);
    bin_search: the two wired by port name (`connect_controller`), what the Simulator runs;
    hardware_station: the YuMi station's hardware twin (`MakeStation(scenario, hardware=True)`,
    an in-process LCM bus);
    hardware_controller: X-Ray on the YuMi with the learned segmenter, camera images only."""
    floating = load_scenario(None, "FloatingGripperBin")
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(floating, target_index=0))
    controller = builder.AddSystem(MakeBinSearchController(
        floating, BinSearchConfig(), sim=SimulationInfo.from_station(station, 0)))
    connect_controller(builder, controller, station)
    search = builder.Build()
    search.set_name("bin_search")

    yumi = load_scenario(None, "YuMiBin")
    hardware_station = MakeStation(yumi, hardware=True, lcm=DrakeLcm("memq://ms_drake_docs"))
    hardware_controller = MakeBinSearchController(yumi, BinSearchConfig(fidelity="full", segmenter="learned"),
                                                  target_shape=HARDWARE_TARGET)
    return dict(bin_station=station, bin_controller=controller, bin_search=search,
                hardware_station=hardware_station, hardware_controller=hardware_controller)
