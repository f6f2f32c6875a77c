"""services: the only package that knows Zenoh: wire messages, ROV and base-station loops, CLI wiring.

Modules:

* :mod:`services.wire` msgpack wire messages (``CloudMsg``, ``StripeMsg``, ``CalibMsg``, ``StatusMsg``), strict
  decoding; its parts: :mod:`services.wire_fields` (packing, field checks, pose maps), :mod:`services.wire_cloud`
  (cloud schema 1), :mod:`services.wire_stripe` (the compact cloud schema 2, the calibration fingerprint);
* :mod:`services.keys` the fleet's key expressions (``FleetKeys``);
* :mod:`services.zconfig` ``--mode/--connect/--listen/--config`` -> ``zenoh.Config`` (multicast scouting off);
* :mod:`services.imu`, :mod:`services.posetrack` IMU sources (sim, CSV, OpenROV serial) and pose interpolation;
* :mod:`services.sources`, :mod:`services.simsource` frame sources (recorded dive, video, camera, simulator);
* :mod:`services.rov` the ROV service;
* :mod:`services.base` the base station's Zenoh wiring, composed of :mod:`services.ledger` (robot records, the
  state file, acknowledgements), :mod:`services.mapfeed` (the map queue, worker and publication, with
  :mod:`services.map_thread` and :mod:`services.mapfeed_views`) and
  :mod:`services.calibbook` (the robots' calibrations, for clouds sent as stripe rows);
* :mod:`services.testnet` the in-process test network; :mod:`services.demo` ``lrsensor demo``;
* :mod:`services.signals` SIGINT/SIGTERM -> a stop event, so every session is closed;
* issue 7 (faults, outbox, acknowledgements, secure profile): :mod:`services.outbox`,
  :mod:`services.delivery` (the ROV's sink: publisher, ack polls, its thread), composed of
  :mod:`services.delivery_link` (what the acknowledgements show of the link), :mod:`services.delivery_book`
  (per-cloud bookkeeping and the counters) and :mod:`services.delivery_pacing` (what may go out: live room,
  re-sends, probes); :mod:`services.wallclock` (the robot's wall clock); :mod:`services.certs`.

The ROV side (``rov``, ``wire``, ``imu``, ``sources``) imports neither Open3D nor ``mapping``.
"""
