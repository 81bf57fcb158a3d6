"""``minetwin sizes``: the 16 size classes and a blast fragmentation curve."""

from __future__ import annotations


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "sizes", help="print the size classes and a Swebrec blast distribution",
        description="Print the 16 logarithmic size classes (d_k = 1e-5 m * 10^(k/3), k = 0..15) with the "
                    "class fractions of a Swebrec blast fragmentation curve, and its D50/D80.")
    parser.add_argument("--x50", type=float, default=0.1, help="median fragment size [m] (0.1)")
    parser.add_argument("--x-max", type=float, default=1.0, help="largest fragment [m] (1.0)")
    parser.add_argument("--b", type=float, default=2.0, help="Swebrec undulation exponent (2.0)")
    parser.set_defaults(handler=run)


def run(args) -> int:
    from cosim import sizes

    f = sizes.swebrec(args.x50, args.x_max, args.b)
    passing = sizes.passing(f)
    print(f"{'class':>5} {'d_k [mm]':>10} {'f_k':>8} {'passing':>8}")
    for k, (d, fk, p) in enumerate(zip(sizes.DIAMETERS, f, passing)):
        print(f"{k:>5} {d * 1e3:>10.3f} {fk:>8.4f} {p:>8.4f}")
    print(f"D50 = {sizes.d_passing(f, 0.5) * 1e3:.1f} mm, "
          f"D80 = {sizes.d_passing(f, 0.8) * 1e3:.1f} mm, "
          f"mean d.f = {sizes.mean_diameter(f) * 1e3:.1f} mm")
    return 0
