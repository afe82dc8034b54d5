"""``python -m cpl_keras.graph`` (``cpl-graph``): print and draw the Lambda
camera graph of a model (``cpl_keras.graph``)."""

from __future__ import annotations

import os

from cpl_keras import cli, files, models
from cpl_keras.graph import PROG, camera_graph, draw_graph, format_table, to_dot
from cpl_keras.models import BACKBONES, variants


def main(argv=None, prog=PROG):
    with_graph = [spec.name for spec in variants.SPECS if spec.camera_graph]
    parser = cli.Parser(prog=prog, description="Show the Lambda camera graph of a model.")
    parser.add_argument("--variant", default="cpl-a",
                        help=f"{' or '.join(with_graph)} (default cpl-a)")
    parser.add_argument("--backbone", default="small",
                        help=f"{', '.join(BACKBONES)} (default small: the graph is the same, "
                        "it builds fast)")
    parser.add_argument("--image-size", type=int, default=112,
                        help="square input side of the model drawn (default 112)")
    parser.add_argument("--as-released", action="store_true", help="the released code's graph")
    parser.add_argument("--out", type=cli.path, default=os.path.join("runs", "camera_graph.png"),
                        help="diagram file (.png, .svg or .pdf; default runs/camera_graph.png, "
                        "git-ignored; docs/camera_graph.png is made with --out)")
    parser.add_argument("--dot", help="also write the graph as Graphviz text to this file "
                        "(dot -Tpng draws it; docs/camera_graph.dot is made with --dot)")
    args = parser.parse_args(argv)
    try:
        if args.variant not in with_graph:
            raise ValueError(f"only {' and '.join(with_graph)} have a camera graph, "
                             f"not {args.variant!r}")
        if os.path.splitext(args.out)[1].lower() not in (".png", ".svg", ".pdf"):
            raise ValueError(f"--out must end in .png, .svg or .pdf: {args.out}")
        outputs = [cli.check_output_file(p) for p in (args.out, args.dot) if p is not None]
        if len({os.path.abspath(p) for p in outputs}) < len(outputs):
            raise ValueError(f"--dot and --out name the same file: {args.dot}")
        model = models.build_model(args.variant, backbone=args.backbone,
                                   image_size=args.image_size, as_released=args.as_released)
    except ValueError as error:
        return cli.fail(prog, error)
    graph = camera_graph(model)
    mode = "as released" if args.as_released else "as the paper writes it"
    print(f"Camera graph of {args.variant} ({mode}): {len(graph)} Lambda layers, "
          f"loss '{model.loss_mode}'")
    print(format_table(graph))
    detached = sorted({name for g in graph for name in g["detached"]})
    if detached:
        print(f"The graph reads {', '.join(detached)} through stop_gradient: the X, Y, Z terms "
              "of the loss train only the pixel heads u, v (exact disentangling of Eq. 7).")
    title = f"{args.variant} camera graph ({mode}): Eqs. 4a-5c as Lambda layers"
    writers = {args.out: ("diagram", lambda: draw_graph(graph, args.out, title))}
    if args.dot:
        writers[args.dot] = ("Graphviz text", lambda: files.write_text(args.dot, to_dot(graph, title)))
    for path, (what, write) in writers.items():
        try:
            cli.make_parent(path)  # (runs/, the default's folder, may not exist yet)
            write()
        except OSError as error:
            return cli.fail(prog, f"cannot write {path}: {error.strerror or error}")
        print(f"{what} written to {path}")
    return 0


if __name__ == "__main__":
    cli.run(main, PROG)
