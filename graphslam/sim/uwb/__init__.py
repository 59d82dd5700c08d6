"""The UWB network of Paper 003 in simulation: clocks and gradient sync (``clock``), TDMA
Alg. 1 (``tdma``), links, frames and two-way ranging (``radio``), the cycle (``network``),
and the scenarios (``scenarios``: the paper's seven-tag experiment, a crowd surveying)."""
