"""A second actuator, written as an Abaqus user would write it (not by ``write_inp``): a
fiber-reinforced bending actuator with a square channel.

Body 12 x 12 x 40 mm (x, y, z) of 3 x 3 x 5 C3D20H bricks (4 x 4 x 8 mm); the middle column of the
lowest four layers is left out, a 4 x 4 x 32 mm channel closed by the top layer and, at z = 0, by the
clamped base. Three straight T3D2 fibers run along z at y = 1 mm (x = 2, 6, 10 mm) from the base to z = 30 mm,
embedded in the bricks (an embedded node's host bricks must not hold rigid-body nodes, so they end
below the top layer): a strain-limiting layer on the -y side, so the pressurized channel bends the actuator
towards -y. The top face is one rigid body (``*RIGID BODY``, a free reference node). Pressure on the
channel's walls and ceiling (``*DSLOAD`` on ``*SURFACE`` faces S1/S3/S4/S5/S6), Neo-Hookean silicone
(``*HYPERELASTIC, NEO HOOKE``, D1 = 0.02 per MPa: K/mu = 1000), cotton fibers (``*ELASTIC``).

Node ids encode the grid: ``1 + i + 25 j + 625 k`` on the 25 x 25 x 81 grid of corner and mid-edge
positions at half-element spacing (i along x, j along y, k along z); fiber nodes from 90001.
"""

NX, NY, NZ = 3, 3, 5  # bricks along x, y, z
H, LZ = 4.0, 8.0  # brick size across (x, y) and along z, mm
CHANNEL_LAYERS = 4  # the channel: brick (1, 1) of the layers 0..3
FIBER_LENGTH = 30.0  # mm from the base: the fibers end below the top layer, whose bricks hold rigid nodes


def _nid(i: int, j: int, k: int) -> int:
    return 1 + i + 25 * j + 625 * k


def _brick_nodes(ex: int, ey: int, ez: int) -> list[int]:
    """C3D20 node order of brick (ex, ey, ez) on the half-spacing grid: corners 1-4 at the bottom
    (z-), 5-8 at the top, then mid-edge nodes 9-12 (bottom), 13-16 (top), 17-20 (vertical)."""
    i, j, k = 2 * ex, 2 * ey, 2 * ez
    c = [(i, j), (i + 2, j), (i + 2, j + 2), (i, j + 2)]
    m = [(i + 1, j), (i + 2, j + 1), (i + 1, j + 2), (i, j + 1)]
    return ([_nid(a, b, k) for a, b in c] + [_nid(a, b, k + 2) for a, b in c] + [_nid(a, b, k) for a, b in m]
            + [_nid(a, b, k + 2) for a, b in m] + [_nid(a, b, k + 1) for a, b in c])


def _is_channel(ex: int, ey: int, ez: int) -> bool:
    return ex == 1 and ey == 1 and ez < CHANNEL_LAYERS


def channel_deck(c10: float = 0.05, d1: float = 0.02, pressure: float = 0.04, e_fiber: float = 31000.0, area: float = 0.05) -> str:
    bricks = {}
    for ez in range(NZ):
        for ey in range(NY):
            for ex in range(NX):
                if not _is_channel(ex, ey, ez):
                    bricks[1 + ex + NX * ey + NX * NY * ez] = _brick_nodes(ex, ey, ez)
    used = sorted({n for nodes in bricks.values() for n in nodes})
    lines = ["*HEADING", "fiber-reinforced bending actuator with a square channel, mm-MPa-N",
             "** corner and mid-edge nodes of the bricks", "*NODE, NSET=NALL"]
    for n in used:
        i, j, k = (n - 1) % 25, (n - 1) // 25 % 25, (n - 1) // 625
        lines.append(f"{n}, {i * H / 2:.6g}, {j * H / 2:.6g}, {k * LZ / 2:.6g}")
    lines.append("*ELEMENT, TYPE=C3D20H, ELSET=BODY")
    for e, nodes in bricks.items():
        lines.append(f"{e}, " + ", ".join(map(str, nodes[:15])) + ",")
        lines.append("   " + ", ".join(map(str, nodes[15:])))
    lines.append("** three straight fibers along z at y = 1 mm, z = 0..30 mm, 10 two-node trusses each")
    lines.append("*NODE")
    fiber_nodes = []
    for f, x in enumerate((2.0, 6.0, 10.0)):
        row = []
        for s in range(11):
            nid = 90001 + 100 * f + s
            lines.append(f"{nid}, {x:g}, 1., {s * FIBER_LENGTH / 10:g}")
            row.append(nid)
        fiber_nodes.append(row)
    lines.append("*ELEMENT, TYPE=T3D2, ELSET=FIBERS")
    for f, row in enumerate(fiber_nodes):
        for s in range(10):
            lines.append(f"{9001 + 100 * f + s}, {row[s]}, {row[s + 1]}")
    base = [_nid(i, j, 0) for j in range(2 * NY + 1) for i in range(2 * NX + 1) if _nid(i, j, 0) in set(used)]
    top = [_nid(i, j, 2 * NZ) for j in range(2 * NY + 1) for i in range(2 * NX + 1) if _nid(i, j, 2 * NZ) in set(used)]
    lines.append("*NSET, NSET=BASE")
    lines += [", ".join(map(str, base[i : i + 8])) for i in range(0, len(base), 8)]
    lines.append("*NSET, NSET=TOP")
    lines += [", ".join(map(str, top[i : i + 8])) for i in range(0, len(top), 8)]
    lines.append("*NODE\n99999, 6., 6., 40.")
    # the channel's walls and ceiling, faces of the bricks around it (S3 y-, S4 x+, S5 y+, S6 x-, S1 z-)
    walls = []
    for ez in range(CHANNEL_LAYERS):
        e = lambda ex, ey: 1 + ex + NX * ey + NX * NY * ez  # noqa: E731
        walls += [(e(0, 1), "S4"), (e(2, 1), "S6"), (e(1, 0), "S5"), (e(1, 2), "S3")]
    walls.append((1 + 1 + NX * 1 + NX * NY * CHANNEL_LAYERS, "S1"))
    lines.append("*SURFACE, NAME=CHANNEL, TYPE=ELEMENT")
    lines += [f"{e}, {s}" for e, s in walls]
    lines += ["*SOLID SECTION, ELSET=BODY, MATERIAL=SILICONE", "*MATERIAL, NAME=SILICONE",
              "*HYPERELASTIC, NEO HOOKE", f"{c10:g}, {d1:g}", "*SOLID SECTION, ELSET=FIBERS, MATERIAL=COTTON",
              f"{area:g}", "*MATERIAL, NAME=COTTON", "*ELASTIC", f"{e_fiber:g}, 0.3",
              "*EMBEDDED ELEMENT, HOST ELSET=BODY", "FIBERS",
              "*RIGID BODY, NSET=TOP, REF NODE=99999",
              "*BOUNDARY", "BASE, ENCASTRE",
              "*STEP, NLGEOM=YES", "*STATIC", "0.1, 1.0",
              "*DSLOAD", f"CHANNEL, P, {pressure:g}",
              "*NODE PRINT, NSET=TOP", "U", "*END STEP"]
    return "\n".join(lines) + "\n"
