"""Decentralised execution of a trained team: one OS process per agent, one for the world, the
channel's real frames as UDP datagrams between them (docs/deploy.md).

* :mod:`~sparsecomm.deploy.wire`: the datagram around every frame (an 11-byte header and an
  8-byte HMAC-SHA-256 under the team's secret; a silent link sends none), the reports' fixed
  binary layout, the nonce that binds observations to one agent process, the heard map the
  world appends to each observation (which senders spoke to the agent last step), address and
  socket helpers;
* :mod:`~sparsecomm.deploy.faults`: seeded loss, duplication, reordering and garbage on the
  agents' links, and the deadlines of every wait;
* :mod:`~sparsecomm.deploy.core`: what a process computes (the eval draws regenerated from the
  batch key, one agent's step, one receiver's reconstruction, the world's step);
* :mod:`~sparsecomm.deploy.agent`, :mod:`~sparsecomm.deploy.world`: the two processes, each a
  command (``python -m sparsecomm.deploy.agent ...``) that can run on its own host;
* :mod:`~sparsecomm.deploy.args`: the arguments of ``sparsecomm deploy`` (``Deploy``);
* :mod:`~sparsecomm.deploy.launcher`: ``sparsecomm deploy``, everything on one host, with
  restarts, kills on schedule, shutdown and the report;
* :mod:`~sparsecomm.deploy.report`: the metrics and CIs of a world's episodes;
* :mod:`~sparsecomm.deploy.hostile`, :mod:`~sparsecomm.deploy.replay`: peers without the
  team's secret, one forging datagrams, one replaying the team's own (drills of the MAC and
  of the replay rules).

Importing this package imports no JAX; the processes import it when they start.
"""
