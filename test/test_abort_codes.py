"""Every CiA 301 abort code is known by name and meaning, from one table of meanings."""

from canopen.sdo.exceptions import SdoAbortedError
import pytest

from cbcan_ros.core.sdo import abort_codes

FATEK_TABLE = {  # the Fatek CBCAN document's table 3
    0x05040000, 0x06020000, 0x06010002, 0x06040047, 0x06010000, 0x06070010, 0x05040001,
    0x05030000, 0x06070012, 0x06010001, 0x05040005}


def test_every_code_of_the_library_table_has_a_name():
    assert set(abort_codes.NAMES) == set(SdoAbortedError.CODES)
    assert len(abort_codes.NAMES) == 31
    assert len(set(abort_codes.NAMES.values())) == 31, 'names are unique'


@pytest.mark.parametrize('code', sorted(FATEK_TABLE | {0x060A0023, 0x08000024}))
def test_codes_from_the_seed_documents_are_described(code):
    assert abort_codes.describe(code).startswith(f'0x{code:08X} {abort_codes.NAMES[code]}: ')


def test_description_carries_name_and_meaning():
    assert abort_codes.describe(0x06020000) == (
        '0x06020000 NOT_EXIST: Object does not exist')


def test_unknown_code_is_described_as_device_specific():
    assert 'UNKNOWN' in abort_codes.describe(0x12345678)
