"""bench/profile_step.py: reading a compiled module's HLO and classifying its ops (no timing)."""

import importlib.util
import os

PATH = os.path.join(os.path.dirname(os.path.dirname(__file__)), "bench", "profile_step.py")
spec = importlib.util.spec_from_file_location("profile_step", PATH)
profile = importlib.util.module_from_spec(spec)
spec.loader.exec_module(profile)

HLO = """
%fused_computation.7 (param_0.7: f32[32,55,55,16], param_1.7: f32[53,53,16,32]) -> f32[32,3,3,32] {
  %param_0.7 = f32[32,55,55,16]{3,2,1,0} parameter(0)
  %param_1.7 = f32[53,53,16,32]{3,2,1,0} parameter(1)
  ROOT %convolution.400 = f32[32,3,3,32]{3,2,1,0} convolution(%param_0.7, %param_1.7), window={size=53x53}, dim_labels=b01f_01io->b01f
}

%fused_computation.8 (param_0.8: f32[16,4]) -> f32[16,4] {
  %param_0.8 = f32[16,4]{1,0} parameter(0)
  ROOT %maximum.1 = f32[16,4]{1,0} maximum(%param_0.8, %param_0.8), metadata={op_name="jit(train_step)/jvp(left_tower)/stem_relu/max"}
}

ENTRY %main.9 (a: f32[32,55,55,16], b: f32[53,53,16,32], c: f32[16,4]) -> f32[32,3,3,32] {
  %ynn_fusion.56 = f32[32,3,3,32]{3,2,1,0} fusion(%a, %b), kind=kCustom, calls=%fused_computation.7
  %loop_fusion.2 = f32[16,4]{1,0} fusion(%c), kind=kLoop, calls=%fused_computation.8
  %add.3 = f32[16,4]{1,0} add(%c, %c), metadata={op_name="jit(train_step)/adam/add"}
}
"""


def test_instruction_table_names_fusions_by_what_they_hold():
    table = profile.instruction_table(HLO)
    assert table["ynn_fusion.56"][:2] == ("convolution-fusion", "f32[32,3,3,32]{3,2,1,0}")
    assert table["loop_fusion.2"][0] == "fusion"
    assert table["loop_fusion.2"][2] == "jit(train_step)/jvp(left_tower)/stem_relu/max"
    assert table["add.3"][2] == "jit(train_step)/adam/add"


def test_classify_by_pass_and_layer_class():
    classes = {"stem_conv": "Conv2D", "stem_bn": "BatchNormalization", "conv2d_1": "PatchConv2D"}
    classify = profile.classify
    assert classify("jit(train_step)/jvp(left)/stem_conv/conv_general_dilated", classes) == (
        "forward", "convolution")
    assert classify("jit(train_step)/transpose(jvp(left))/stem_bn/reduce_sum", classes) == (
        "backward", "BatchNorm")
    assert classify("jit(train_step)/transpose(jvp(left))/conv2d_1/dot_general", classes) == (
        "backward", "convolution (PatchConv2D layers)")
    assert classify("jit(train_step)/adam/add", classes) == ("optimizer", "Adam update")
    assert classify("jit(train_step)/jvp(compile_loss)/mae/abs", classes) == ("forward", "loss")
    assert classify("", classes) == ("other", "other")
