"""The json codec: the plugin kit's codec suite, then what is its own: the JSON it writes, byte
for byte, base64 for bytes, its options, and what it refuses."""

from __future__ import annotations

import json

import pytest
from geometry_msgs.msg import Twist, Vector3
from rosgate_codec_json import JsonCodec
from rosgate_testing import CodecConformance
from sensor_msgs.msg import Image
from std_msgs.msg import String

from rosgate import CodecError, OptionError


class TestJsonConformance(CodecConformance):
    codec = JsonCodec


class TestIndentedJsonConformance(CodecConformance):
    codec = JsonCodec
    options = {"indent": 2, "ascii": False}


def test_a_message_is_an_object_of_its_fields_in_msg_order():
    data = JsonCodec(Twist, {}).encode(Twist(linear=Vector3(x=1.5), angular=Vector3(z=-2.0)))
    assert data == (b'{"linear":{"x":1.5,"y":0.0,"z":0.0},'
                    b'"angular":{"x":0.0,"y":0.0,"z":-2.0}}')


def test_bytes_travel_as_base64_text():
    image = Image(height=1, width=3, encoding="mono8", step=3, data=b"\x00\xff\x10")
    tree = json.loads(JsonCodec(Image, {}).encode(image))
    assert tree["data"] == "AP8Q"
    assert JsonCodec(Image, {}).decode(json.dumps(tree).encode()) == image


def test_options_indent_and_ascii():
    codec = JsonCodec(String, {"indent": 2, "ascii": False})
    assert codec.encode(String(data="é")) == '{\n  "data": "é"\n}'.encode()
    assert JsonCodec(String, {}).encode(String(data="é")) == b'{"data":"\\u00e9"}'


@pytest.mark.parametrize("options, key, message", [
    ({"indent": -1}, "indent", "expected an integer 0..8 or null, got -1"),
    ({"indent": "two"}, "indent", "expected an integer 0..8 or null, got 'two'"),
    ({"ascii": "no"}, "ascii", "expected true or false, got 'no'"),
    ({"indnet": 2}, "indnet", "unknown key 'indnet' (did you mean 'indent'?)"),
])
def test_wrong_options(options, key, message):
    with pytest.raises(OptionError) as error:
        JsonCodec(String, options)
    assert (error.value.key, error.value.message) == (key, message)


@pytest.mark.parametrize("data, says", [
    (b'{"data": 5}', "std_msgs/String: data: expected string, got 5"),
    (b'{"dta": "x"}', "std_msgs/String: dta: unknown field of std_msgs/String"),
    (b'["x"]', "expected a map of std_msgs/String fields, got an array of 1"),
    (b'{"data": "x"} {}', "not one JSON value: Extra data"),
    (b'{"data": "\\ud800"}', "got text with an unpaired surrogate"),
    (b"\xff", "not one JSON value"),
])
def test_what_it_refuses_is_a_codec_error_naming_the_field(data, says):
    with pytest.raises(CodecError, match=says.replace("[", r"\[")):
        JsonCodec(String, {}).decode(data)


def test_base64_that_is_not_is_refused_at_its_field():
    with pytest.raises(CodecError, match=r"sensor_msgs/Image: data: expected sequence<uint8> "
                                         r"\(base64 text\), got str 'A\?'"):
        JsonCodec(Image, {}).decode(b'{"data": "A?"}')
