"""Human-VDM core library: the generic DAG engine (:mod:`humanvdm_core.workflow`) and, around it,
the reconstruction modules (cameras, imaging, body models, Gaussian splatting, rendering, models).

Stage executables under ``stages/`` are thin wrappers around this package.
"""
