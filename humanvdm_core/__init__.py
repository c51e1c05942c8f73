"""Human-VDM core library: artifact store, scheduler, cameras, imaging, rendering.

Stage executables under ``stages/`` are thin wrappers around this package.
"""
