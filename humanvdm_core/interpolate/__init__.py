"""The ``interpolate`` stage's library: :mod:`.core` interpolates an orbit's frame set (the
contract, schedules, the ``embedded`` backend, backend dispatch); the model backends beside it:
:mod:`.rife` RIFE v4.6 IFNet (Practical-RIFE ``flownet.pkl``, arbitrary-time), :mod:`.pervfi`
PerVFI (v00 generator, ×2) with its flow estimator :mod:`.raft` (RAFT). Shared checkpoint tools are
in :mod:`humanvdm_core.models`."""
