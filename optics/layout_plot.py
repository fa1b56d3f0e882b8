"""A Zemax-style 2-D layout: the telescope's cross-section in the x-z plane (the fold plane) with ray fans.

Mechanical parts are drawn from :mod:`optics.layout`; rays come from the sequential tracer, so the picture
shows exactly what is traced (rays stop where they are blocked).
"""

from __future__ import annotations

import numpy as np

from .sequential import DETECTOR_MISS, OK, SequentialTracer


def plot_layout(tracer: SequentialTracer, path, fields_deg=(0.0, 0.8, 1.55), rays_per_field: int = 11,
                title: str = ""):
    """Cross-section (y = 0) with a fan of ``rays_per_field`` rays per field angle (field along x); rays
    that an obstruction stops are left out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    L = tracer.layout
    fig, ax = plt.subplots(figsize=(7.5, 10))
    black = {"color": "0.15", "lw": 1.6}
    # tube wall (with the focuser opening on +x), cell, vanes
    zb, zt, R = L.tube_bottom, L.tube_top, L.r_tube
    ax.plot([-R, -R], [zb, zt], **black)
    ax.plot([R, R], [zb, L.z_axis - L.r_focuser], **black)
    ax.plot([R, R], [L.z_axis + L.r_focuser, zt], **black)
    ax.plot([-R, R], [zb, zb], **black)
    for z in L.vane_z:
        ax.plot([-R, -L.r_vane], [z, z], **black)
        ax.plot([L.r_vane, R], [z, z], **black)
    # primary
    r = np.linspace(-L.r_primary, L.r_primary, 200)
    ax.plot(r, L.primary_sag(np.abs(r)), color="tab:blue", lw=2.5)
    # diagonal, holder, spider
    cx, _, cz = L.diag_centre
    b = L.diag_b
    ax.plot([cx - b, cx + b], [cz - b, cz + b], color="tab:blue", lw=2.5)
    ax.plot([cx - b, cx - b, cx + b, cx + b], [cz - b, L.holder_top, L.holder_top, cz + b], **black)
    z0, z1 = L.spider_z
    ax.fill_between([-R, -b, b, R], [z0] * 4, [z1] * 4, color="0.6", alpha=0.5, lw=0)
    # focuser, housing, lenses, detector
    x0 = L.focuser_start_x
    for s in (-1, 1):
        ax.plot([x0, L.x_housing], [L.z_axis + s * L.r_focuser] * 2, **black)
    h = L.housing_half
    ax.plot([L.x_housing, L.x_housing, L.x_detector + 15, L.x_detector + 15, L.x_housing, L.x_housing],
            [L.z_axis + L.r_focuser, L.z_axis + h, L.z_axis + h, L.z_axis - h, L.z_axis - h,
             L.z_axis - L.r_focuser], **black)
    for srf in L.lenses:
        t = np.linspace(-srf.semi_diameter_mm, srf.semi_diameter_mm, 60)
        if srf.radius_mm == 0:
            sag = np.zeros_like(t)
        else:
            Rc = srf.radius_mm
            sag = Rc - np.sign(Rc) * np.sqrt(np.maximum(Rc * Rc - t * t, 0))
        ax.plot(srf.x_mm + sag, L.z_axis + t, color="tab:cyan", lw=1.5)
    hu = L.detector_half[0]
    ax.plot([L.x_detector] * 2, [L.z_axis - hu, L.z_axis + hu], color="tab:red", lw=3)
    # ray fans
    colours = ["tab:green", "tab:orange", "tab:purple", "tab:brown"]
    # the fan runs just beside the section plane: the spider vane in y = 0 would block all of it
    px = np.linspace(-L.r_primary * 0.98, L.r_primary * 0.98, rays_per_field)
    py = np.full_like(px, L.spider_half_width + 2.0)
    for k, fdeg in enumerate(fields_deg):
        pts, lost = tracer.paths((fdeg, 0.0), px, py)
        first = True
        for i in range(len(px)):
            if lost[i] not in (OK, DETECTOR_MISS):
                continue                                   # blocked rays are not drawn
            ax.plot(pts[i, :, 0], pts[i, :, 2], color=colours[k % 4], lw=0.5, alpha=0.8,
                    label=f"{fdeg:g} deg" if first else None)
            first = False
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm] (focuser side +x)")
    ax.set_ylabel("z [mm] (up the tube)")
    ax.set_title(title or f"{tracer.design.name}: layout (y = 0 section)")
    ax.legend(loc="upper left", fontsize=8)
    ax.set_xlim(-R - 30, L.x_detector + 40)
    ax.set_ylim(zb - 30, zt + 60)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
