"""Bus description files (ros2_canopen's bus.yml) read as ros2_canopen and dcfgen mean them.

ros2_canopen's own example files (test/bus_descriptions/, see its README) load with every
node, id, driver, SDO write and PDO mapping they give; the keys this gateway does not
implement are listed by path; every wrong value is refused with one message naming the file,
the key and what is allowed. No ROS is needed.
"""

import os
import pathlib
import textwrap

import pytest

from cbcan_ros.core.boot.description import (
    BusDescription,
    DescriptionError,
    DeviceDescription,
    load,
    MasterDescription,
    parse,
    PdoSetting,
    SdoWrite,
)

EXAMPLES = pathlib.Path(__file__).resolve().parent / 'bus_descriptions'
FOLDER = '/robot/config'  # the folder of the files given as text
PATH = f'{FOLDER}/bus.yml'
SHOWN = repr(PATH)  # the file as messages name it

# What ros2_canopen's CiA 402 examples configure on each drive (cia402.yml's defaults).
CIA402_SDO = (SdoWrite(0x60C2, 1, 50), SdoWrite(0x60C2, 2, -3), SdoWrite(0x6081, 0, 1000),
              SdoWrite(0x6083, 0, 2000))
CIA402_TPDO = (
    PdoSetting(1, transmission=1, mapping=((0x6041, 0), (0x6061, 0))),
    PdoSetting(2, transmission=1, mapping=((0x6064, 0), (0x606C, 0))),
    PdoSetting(3, enabled=False),
    PdoSetting(4, enabled=False),
)
CIA402_RPDO = (
    PdoSetting(1, mapping=((0x6040, 0), (0x6060, 0))),
    PdoSetting(2, mapping=((0x607A, 0), (0x60FF, 0))),
)


def read(text: str) -> BusDescription:
    return parse(textwrap.dedent(text), PATH)


def refused(text: str) -> str:
    with pytest.raises(DescriptionError) as error:
        read(text)
    return str(error.value)


def example(name: str) -> str:
    return str(EXAMPLES / name)


# ros2_canopen's example files


def test_cia402_nodes_under_nodes_with_defaults():
    bus = load(example('cia402.yml'))
    assert bus.path == example('cia402.yml')
    assert bus.master == MasterDescription(node_id=1, sync_period=10000,
                                           given=frozenset({'node_id', 'sync_period'}))
    assert bus.devices == (DeviceDescription(
        name='cia402_device_1', node_id=2, dcf=example('cia402_slave.eds'), driver='drive',
        driver_name='ros2_canopen::Cia402Driver', revision_number=0, sdo=CIA402_SDO,
        tpdo=CIA402_TPDO, rpdo=CIA402_RPDO),)
    assert bus.unsupported == ('defaults.period', 'defaults.boot_timeout_ms',
                               'nodes.cia402_device_1.namespace')


def test_simple_proxies_at_the_top_level():
    bus = load(example('simple.yml'))
    assert bus.master == MasterDescription(node_id=1, given=frozenset({'node_id'}))
    assert bus.devices == tuple(
        DeviceDescription(name=f'proxy_device_{node_id - 1}', node_id=node_id,
                          dcf=example('simple.eds'), driver='proxy',
                          driver_name='ros2_canopen::ProxyDriver')
        for node_id in (2, 3))
    assert bus.unsupported == (
        'proxy_device_1.polling', 'proxy_device_1.period', 'proxy_device_1.boot_timeout_ms',
        'proxy_device_1.remappings', 'proxy_device_2.polling', 'proxy_device_2.period',
        'proxy_device_2.boot_timeout_ms')


def test_simple_diagnostics_proxies_under_nodes_from_defaults():
    bus = load(example('simple_diagnostics.yml'))
    assert [(device.name, device.node_id, device.driver, device.dcf) for device in bus.devices] \
        == [('proxy_device_1', 2, 'proxy', example('simple.eds')),
            ('proxy_device_2', 3, 'proxy', example('simple.eds'))]
    assert bus.unsupported == ('defaults.polling', 'defaults.period', 'defaults.diagnostics')


def test_robot_control_drives_at_the_top_level_with_their_own_lists():
    bus = load(example('robot_control.yml'))
    mode = SdoWrite(0x6060, 0, 7)
    rpdo = (CIA402_RPDO[0], PdoSetting(2, mapping=((0x607A, 0),)))  # 0x60FF commented out
    assert bus.devices == tuple(
        DeviceDescription(name=name, node_id=node_id, dcf=example('cia402_slave.eds'),
                          driver='drive', driver_name='ros2_canopen::Cia402Driver',
                          revision_number=0, sdo=CIA402_SDO + (mode,), tpdo=CIA402_TPDO[:2],
                          rpdo=rpdo)
        for name, node_id in (('joint_1', 2), ('joint_2', 3)))
    assert bus.unsupported == ('joint_1.period', 'joint_1.position_mode', 'joint_2.period',
                               'joint_2.position_mode', 'joint_2.switching_state')


def test_lifecycle_drivers_are_drives():
    bus = load(example('cia402_lifecycle.yml'))
    assert bus.master.sync_period == 20000
    (device,) = bus.devices
    assert (device.name, device.node_id, device.driver, device.driver_name) == (
        'cia402_device_1', 2, 'drive', 'ros2_canopen::LifecycleCia402Driver')
    assert device.sdo == CIA402_SDO[:2]
    assert (device.tpdo, device.rpdo) == (CIA402_TPDO, CIA402_RPDO)
    assert bus.unsupported == ('cia402_device_1.period', 'cia402_device_1.enable_lazy_load')


def test_multichannel_scales_and_channel_keys():
    bus = load(example('cia402_multichannel_system.yml'))
    (device,) = bus.devices
    assert device.dcf == example('cia402_slave_multichannel.eds')
    assert dict(device.scales) == {'scale_pos_to_dev': 1000.0, 'scale_pos_from_dev': 0.001,
                                   'scale_vel_to_dev': 1000.0, 'scale_vel_from_dev': 0.001,
                                   'offset_pos_to_dev': 0.0, 'offset_pos_from_dev': 0.0}
    assert [setting.mapping for setting in device.tpdo] == [
        ((0x6041, 0), (0x6061, 0)), ((0x6064, 0), (0x606C, 0)),
        ((0x6841, 0), (0x6861, 0)), ((0x6864, 0), (0x686C, 0))]
    assert [setting.mapping for setting in device.rpdo] == [
        ((0x6040, 0), (0x6060, 0)), ((0x607A, 0), (0x60FF, 0)),
        ((0x6840, 0), (0x6860, 0)), ((0x687A, 0), (0x68FF, 0))]
    assert device.sdo[4:] == (SdoWrite(0x68C2, 1, 50), SdoWrite(0x68C2, 2, -3),
                              SdoWrite(0x6881, 0, 1000), SdoWrite(0x6883, 0, 2000))
    node = 'nodes.cia402_multichannel_device'
    assert bus.unsupported == tuple(f'{node}.{key}' for key in (
        'period', 'num_channels', 'channel_names', 'channels',
        'switching_state', 'homing_timeout_seconds'))


def test_ros2_canopen_bad_files_are_refused():
    with pytest.raises(DescriptionError) as duplicate:
        load(example('bad_driver_duplicate.yml'))
    assert str(duplicate.value) == (f"{example('bad_driver_duplicate.yml')!r}: not valid YAML: "
                                    f"'proxy_device_1' is given twice (line 9, column 1)")
    with pytest.raises(DescriptionError) as no_id:
        load(example('bad_driver_no_id.yml'))
    assert str(no_id.value) == (f"{example('bad_driver_no_id.yml')!r}: proxy_device_1: "
                                f"no node_id: allowed 1..127")


def test_proxy_sdo_file_keeps_the_defaults_sdo_list():
    bus = load(example('proxy_sdo.yml'))
    assert bus.master == MasterDescription(node_id=1, heartbeat_producer=100,
                                           given=frozenset({'node_id', 'heartbeat_producer'}))
    first, second = bus.devices
    # ros2_canopen issue #257: the sdo list of the defaults reaches every node.
    assert first == DeviceDescription(
        name='proxy_device_1', node_id=2, dcf=example('simple.eds'), driver='proxy',
        driver_name='ros2_canopen::ProxyDriver', heartbeat_producer=1000,
        sdo=(SdoWrite(0x2003, 0, 0x12345678), SdoWrite(0x2002, 0, '0x0000FFFF')))
    assert second == DeviceDescription(
        name='proxy_device_2', node_id=3, dcf=example('simple.eds'), driver='proxy',
        driver_name='ros2_canopen::ProxyDriver', heartbeat_producer=500,
        sdo=(SdoWrite(0x2003, 0, 7),),
        tpdo=(PdoSetting(1, cob_id=0x183, transmission=254, event_timer=100,
                         mapping=((0x2002, 0),)),))
    assert bus.unsupported == ()


# defaults, node forms, paths


def test_a_node_key_wins_over_the_defaults_and_its_list_replaces_theirs():
    bus = read("""
        defaults:
          heartbeat_producer: 1000
          mandatory: true
          sdo: [{index: 0x2000, sub_index: 1, value: 1}, {index: 0x2000, sub_index: 2, value: 2}]
          tpdo: {1: {transmission: 1}, 2: {enabled: false}}
        nodes:
          own:
            node_id: 5
            heartbeat_producer: 200
            sdo: [{index: 0x2001, value: 9.5}]
            tpdo: {3: {event_timer: 10}}
          inherits:
            node_id: 4
    """)
    inherits, own = bus.devices
    assert (inherits.name, inherits.heartbeat_producer, inherits.mandatory) == (
        'inherits', 1000, True)
    assert inherits.sdo == (SdoWrite(0x2000, 1, 1), SdoWrite(0x2000, 2, 2))
    assert inherits.tpdo == (PdoSetting(1, transmission=1), PdoSetting(2, enabled=False))
    assert (own.name, own.heartbeat_producer, own.mandatory) == ('own', 200, True)
    assert own.sdo == (SdoWrite(0x2001, 0, 9.5),)
    assert own.tpdo == (PdoSetting(3, event_timer=10),)


def test_both_node_forms_describe_the_same_devices():
    nested = read("""
        master: {node_id: 1}
        defaults: {dcf: drive.eds, driver: "ros2_canopen::Cia402Driver"}
        nodes:
          left: {node_id: 3, boot: false}
          right: {node_id: 2}
    """)
    flat = read("""
        master: {node_id: 1}
        right: {node_id: 2, dcf: drive.eds, driver: "ros2_canopen::Cia402Driver"}
        left: {node_id: 3, dcf: drive.eds, driver: "ros2_canopen::Cia402Driver", boot: false}
    """)
    assert nested == flat
    assert [(device.name, device.node_id, device.boot, device.dcf) for device in flat.devices] \
        == [('right', 2, True, f'{FOLDER}/drive.eds'), ('left', 3, False, f'{FOLDER}/drive.eds')]


def test_anchor_holders_are_skipped_and_merges_work():
    bus = read("""
        .drive: &drive {dcf: drive.eds, driver: "ros2_canopen::Cia402Driver", mandatory: true}
        master: {node_id: 1}
        left: {<<: *drive, node_id: 2, mandatory: false}
    """)
    assert bus.devices == (DeviceDescription(
        name='left', node_id=2, dcf=f'{FOLDER}/drive.eds', driver='drive',
        driver_name='ros2_canopen::Cia402Driver', mandatory=False),)
    assert bus.unsupported == ()


@pytest.mark.parametrize('options, node, dcf', [
    ('', 'dcf: a.eds', f'{FOLDER}/a.eds'),
    ('', 'dcf: ../eds/a.eds', '/robot/eds/a.eds'),
    ('', 'dcf: /opt/eds/a.eds', '/opt/eds/a.eds'),
    ('options: {dcf_path: eds}', 'dcf: a.eds', f'{FOLDER}/eds/a.eds'),
    ('options: {dcf_path: /opt/eds}', 'dcf: a.eds', '/opt/eds/a.eds'),
    ('options: {dcf_path: /opt/eds}', 'dcf: /srv/a.eds', '/srv/a.eds'),
    ('options: {dcf_path: "@BUS_CONFIG_PATH@"}', 'dcf: a.eds', f'{FOLDER}/a.eds'),
    ('options: {dcf_path: "@BUS_CONFIG_PATH@/eds"}', 'dcf: a.eds', f'{FOLDER}/eds/a.eds'),
    ('', 'dcf: "@BUS_CONFIG_PATH@/a.eds"', f'{FOLDER}/a.eds'),
    ('options: {dcf_path: /opt/eds}', '{dcf: a.eds, dcf_path: own}', f'{FOLDER}/own/a.eds'),
    ('options: {dcf_path: /opt/eds}', '{dcf: a.eds, dcf_path: /x}', '/x/a.eds'),
    ('', 'driver: x', ''),
    ('', 'dcf: ""', ''),
])
def test_dcf_paths(options, node, dcf):
    bus = read(f"""
        {options}
        nodes:
          one: {{node_id: 1, {node.strip('{}')}}}
    """)
    assert bus.devices[0].dcf == dcf


def test_a_relative_file_path_resolves_from_the_current_folder(tmp_path, monkeypatch):
    (tmp_path / 'bus.yml').write_text('one: {node_id: 7, dcf: a.eds}\n')
    monkeypatch.chdir(tmp_path)
    bus = load('bus.yml')
    assert (bus.path, bus.devices[0].dcf) == ('bus.yml', os.path.join(str(tmp_path), 'a.eds'))


# keys and their values


def test_identity_missing_zero_and_given():
    bus = read("""
        nodes:
          missing: {node_id: 1}
          zero: {node_id: 2, vendor_id: 0, product_code: 0, revision_number: 0, serial_number: 0}
          given: {node_id: 3, vendor_id: 0x0000029C, product_code: "0x1234",
                  revision_number: "65537", serial_number: 4294967295}
    """)
    identities = [(device.vendor_id, device.product_code, device.revision_number,
                   device.serial_number) for device in bus.devices]
    assert identities == [(None, None, None, None), (0, 0, 0, 0),
                          (0x29C, 0x1234, 65537, 0xFFFFFFFF)]


@pytest.mark.parametrize('given, restore', [
    ('', 0), ('restore_configuration: 0', 0), ('restore_configuration: 2', 2),
    ('restore_configuration: 0x7F', 0x7F), ('restore_configuration: true', 1),
    ('restore_configuration: false', 0),
])
def test_restore_configuration_is_the_0x1011_subindex(given, restore):
    bus = read(f"""
        nodes:
          one: {{node_id: 1, {given}}}
    """)
    assert bus.devices[0].restore_configuration == restore


def test_flags_defaults_and_values():
    bus = read("""
        nodes:
          plain: {node_id: 1}
          set:
            node_id: 2
            heartbeat_consumer: true
            boot: false
            mandatory: 1
            reset_communication: false
            store_configuration: true
            start: 0
    """)
    flags = [(device.heartbeat_consumer, device.boot, device.mandatory,
              device.reset_communication, device.store_configuration, device.start)
             for device in bus.devices]
    assert flags == [(False, True, False, True, False, True),
                     (True, False, True, False, True, False)]


def test_master_keys_and_which_were_given():
    bus = read("""
        master:
          node_id: "0x7F"
          sync_period: 1000
          heartbeat_producer: 50
          boot_time: 3000
          start_nodes: false
          heartbeat_consumer: false
          driver: "ros2_canopen::MasterDriver"
          package: canopen_master_driver
    """)
    assert bus.master == MasterDescription(
        node_id=127, sync_period=1000, heartbeat_producer=50, boot_timeout=3000,
        start_nodes=False, heartbeat_consumer=False,
        given=frozenset({'node_id', 'sync_period', 'heartbeat_producer', 'boot_timeout',
                         'start_nodes', 'heartbeat_consumer'}))
    assert bus.devices == ()
    assert bus.unsupported == ()
    assert read('master: {boot_timeout: 2000}').master == MasterDescription(
        boot_timeout=2000, given=frozenset({'boot_timeout'}))
    assert read('master:').master == MasterDescription()


def test_pdo_settings():
    bus = read("""
        nodes:
          one:
            node_id: 9
            rpdo:
              "2": {cob_id: "0x309", transmission: 255, mapping: [{index: 0x6040}]}
              1: {cob_id: auto, enabled: false, inhibit_time: 100,
                  mapping: [{index: "0x6060", subindex: "0"}, {index: 0x2000, sub_index: 3}]}
              512: {transmission_type: 1}
    """)
    assert bus.devices[0].rpdo == (
        PdoSetting(1, enabled=False, inhibit_time=100, mapping=((0x6060, 0), (0x2000, 3))),
        PdoSetting(2, cob_id=0x309, transmission=255, mapping=((0x6040, 0),)),
        PdoSetting(512, transmission=1))


def test_sdo_values_keep_their_yaml_type():
    bus = read("""
        nodes:
          one:
            node_id: 1
            sdo:
              - {index: 0x2000, value: 0x10}
              - {index: 0x2001, value: "0x10"}
              - {index: 0x2002, value: 1.5}
              - {index: 0x2003, value: "text"}
              - {index: 0x2004, value: true}
              - {index: 0x2005, subindex: 0xFF, value: -1}
    """)
    assert bus.devices[0].sdo == (
        SdoWrite(0x2000, 0, 16), SdoWrite(0x2001, 0, '0x10'), SdoWrite(0x2002, 0, 1.5),
        SdoWrite(0x2003, 0, 'text'), SdoWrite(0x2004, 0, 1), SdoWrite(0x2005, 0xFF, -1))
    assert type(bus.devices[0].sdo[4].value) is int


def test_drivers():
    bus = read("""
        nodes:
          a: {node_id: 1, driver: "ros2_canopen::Cia402Driver"}
          b: {node_id: 2, driver: "ros2_canopen::LifecycleProxyDriver"}
          c: {node_id: 3, driver: "ros2_canopen::CanopenDriver"}
          d: {node_id: 4}
    """)
    assert [(device.driver, device.driver_name) for device in bus.devices] == [
        ('drive', 'ros2_canopen::Cia402Driver'), ('proxy', 'ros2_canopen::LifecycleProxyDriver'),
        ('', 'ros2_canopen::CanopenDriver'), ('', '')]


def test_unsupported_keys_are_listed_by_path_once():
    bus = read("""
        options: {dcf_path: eds, heartbeat_multiplier: 3}
        master: {node_id: 1, baudrate: 500, driver: x, package: y, start: true}
        defaults: {polling: true, package: canopen_proxy_driver, tpdo: {1: {sync_start: 1}}}
        nodes:
          left_wheel:
            node_id: 2
            polling: false
            error_behavior: {1: 0}
            package: canopen_402_driver
            sdo: [{index: 0x2000, value: 1, comment: x}]
            tpdo:
              1: {sync_start: 3, event_deadline: 5, mapping: [{index: 0x2000, bits: 8}]}
          right_wheel: {node_id: 3}
          caster: {node_id: 4}
    """)
    assert bus.unsupported == (
        'options.heartbeat_multiplier', 'master.baudrate', 'master.start', 'defaults.polling',
        'nodes.left_wheel.polling', 'nodes.left_wheel.error_behavior',
        'nodes.left_wheel.sdo[1].comment', 'nodes.left_wheel.tpdo.1.sync_start',
        'nodes.left_wheel.tpdo.1.event_deadline', 'nodes.left_wheel.tpdo.1.mapping[1].bits',
        'defaults.tpdo.1.sync_start')


# every refusal names the file, the key and what is allowed

ERRORS = [
    ('not-yaml', 'nodes: [unclosed',
     "not valid YAML: expected ',' or ']', but got '<stream end>' (line 1, column 17)"),
    ('key-twice', 'master: {node_id: 1}\nmaster: {node_id: 2}',
     "not valid YAML: 'master' is given twice (line 2, column 1)"),
    ('empty', '', 'nothing (null): allowed a mapping of options, master, defaults and nodes'),
    ('root-list', '- a', 'a list: allowed a mapping of options, master, defaults and nodes'),
    ('options-list', 'options: [a]', 'options: a list: allowed a mapping of keys'),
    ('master-text', 'master: one', "master: 'one' is text: allowed a mapping of keys"),
    ('master-id-zero', 'master: {node_id: 0}',
     'master.node_id: 0 is out of range: allowed an integer 1..127 (or its text, as "0x1A")'),
    ('master-id-255', 'master: {node_id: 255}',
     'master.node_id: 255 is out of range: allowed an integer 1..127 (or its text, as "0x1A")'),
    ('master-sync-text', 'master: {sync_period: fast}',
     "master.sync_period: 'fast' is text: allowed an integer 0..4294967295 µs"),
    ('master-heartbeat-float', 'master: {heartbeat_producer: 1.5}',
     'master.heartbeat_producer: 1.5 is a number: allowed an integer 0..65535 ms'),
    ('master-boot-both', 'master: {boot_time: 1, boot_timeout: 2}',
     'master.boot_time: master.boot_timeout is given too: they are one setting here (the time '
     'a device has to boot), give one'),
    ('master-boot-negative', 'master: {boot_timeout: -1}',
     'master.boot_timeout: -1 is out of range: allowed an integer 0..4294967295 ms'),
    ('master-start-text', 'master: {start_nodes: "yes"}',
     "master.start_nodes: 'yes' is text: allowed true or false"),
    ('nodes-list', 'nodes: [{a: {node_id: 1}}]', 'nodes: a list: allowed a mapping of keys'),
    ('node-number', 'nodes: {a: 5}', 'nodes.a: 5 is an integer: allowed a mapping of keys'),
    ('node-name-number', 'nodes: {5: {node_id: 5}}',
     'nodes.5: 5 is an integer: a node is named by text'),
    ('top-level-scalar', 'version: 2', 'version: 2 is an integer: allowed a mapping of keys'),
    ('top-level-beside-nodes', 'nodes: {a: {node_id: 1}}\nb: {node_id: 2}',
     "b: a node at the top level beside 'nodes:': give every node under nodes "
     "(ros2_canopen's cogen drops it)"),
    ('no-node-id', 'nodes: {a: {dcf: a.eds}}', 'nodes.a: no node_id: allowed 1..127'),
    ('node-id-zero', 'nodes: {a: {node_id: 0}}',
     'nodes.a.node_id: 0 is out of range: allowed an integer 1..127 (or its text, as "0x1A")'),
    ('node-id-128', 'a: {node_id: 128}',
     'a.node_id: 128 is out of range: allowed an integer 1..127 (or its text, as "0x1A")'),
    ('node-id-text', 'nodes: {a: {node_id: two}}',
     "nodes.a.node_id: 'two' is not a number: allowed an integer 1..127 (or its text, as "
     '"0x1A")'),
    ('node-id-bool', 'nodes: {a: {node_id: true}}',
     'nodes.a.node_id: True is a boolean: allowed an integer 1..127 (or its text, as "0x1A")'),
    ('node-id-twice', 'nodes: {a: {node_id: 4}, b: {node_id: "0x04"}}',
     'nodes.b.node_id: 4 is also the node_id of a: each node needs its own'),
    ('node-id-in-defaults', 'defaults: {node_id: 4}\nnodes: {a: {}, b: {}}',
     'nodes.b.node_id: 4 is also the node_id of a: each node needs its own'),
    ('heartbeat-text', 'nodes: {a: {node_id: 1, heartbeat_producer: "100"}}',
     "nodes.a.heartbeat_producer: '100' is text: allowed an integer 0..65535 ms"),
    ('heartbeat-range', 'nodes: {a: {node_id: 1, heartbeat_producer: 70000}}',
     'nodes.a.heartbeat_producer: 70000 is out of range: allowed an integer 0..65535 ms'),
    ('defaults-heartbeat', 'defaults: {heartbeat_producer: [1]}\nnodes: {a: {node_id: 1}}',
     'defaults.heartbeat_producer: a list: allowed an integer 0..65535 ms'),
    ('flag-two', 'nodes: {a: {node_id: 1, boot: 2}}',
     'nodes.a.boot: 2 is an integer: allowed true or false'),
    ('dcf-number', 'nodes: {a: {node_id: 1, dcf: 5}}',
     'nodes.a.dcf: 5 is an integer: allowed a path'),
    ('dcf-path-variable', 'options: {dcf_path: "@CMAKE_INSTALL_PREFIX@/eds"}',
     "options.dcf_path: '@CMAKE_INSTALL_PREFIX@/eds' names @CMAKE_INSTALL_PREFIX@: only "
     "@BUS_CONFIG_PATH@ (the file's folder) is known here"),
    ('driver-number', 'nodes: {a: {node_id: 1, driver: 402}}',
     'nodes.a.driver: 402 is an integer: allowed a class name, as '
     '"ros2_canopen::Cia402Driver"'),
    ('vendor-negative', 'nodes: {a: {node_id: 1, vendor_id: -1}}',
     'nodes.a.vendor_id: -1 is out of range: allowed an integer 0..0xFFFFFFFF (or its text, '
     'as "0x1A")'),
    ('restore-range', 'nodes: {a: {node_id: 1, restore_configuration: 128}}',
     'nodes.a.restore_configuration: 128 is out of range: allowed an integer 0..127'),
    ('scale-text', 'nodes: {a: {node_id: 1, scale_pos_to_dev: big}}',
     "nodes.a.scale_pos_to_dev: 'big' is text: allowed a number"),
    ('sdo-mapping', 'nodes: {a: {node_id: 1, sdo: {index: 1}}}',
     'nodes.a.sdo: a mapping: allowed a list (- entries)'),
    ('sdo-entry-number', 'nodes: {a: {node_id: 1, sdo: [5]}}',
     'nodes.a.sdo[1]: 5 is an integer: allowed a mapping of keys'),
    ('sdo-no-index', 'nodes: {a: {node_id: 1, sdo: [{sub_index: 1, value: 1}]}}',
     'nodes.a.sdo[1]: no index: allowed an object index 0x0001..0xFFFF'),
    ('sdo-no-value', 'nodes: {a: {node_id: 1, sdo: [{index: 0x2000}]}}',
     'nodes.a.sdo[1]: no value: allowed a number or text'),
    ('sdo-value-list', 'nodes: {a: {node_id: 1, sdo: [{index: 0x2000, value: [1]}]}}',
     'nodes.a.sdo[1].value: a list: allowed a number or text'),
    ('sdo-index-range', 'nodes: {a: {node_id: 1, sdo: [{index: 0x10000, value: 1}]}}',
     'nodes.a.sdo[1].index: 65536 is out of range: allowed an integer 1..0xFFFF (or its text, '
     'as "0x1A")'),
    ('sdo-subindex-range',
     'defaults: {sdo: [{index: 1, value: 1}, {index: 2, sub_index: 256, value: 1}]}\n'
     'nodes: {a: {node_id: 1}}',
     'defaults.sdo[2].sub_index: 256 is out of range: allowed an integer 0..255 (or its text, '
     'as "0x1A")'),
    ('sdo-subindex-twice',
     'nodes: {a: {node_id: 1, sdo: [{index: 1, sub_index: 1, subindex: 1, value: 1}]}}',
     'nodes.a.sdo[1].subindex: sub_index is given too: give one'),
    ('tpdo-list', 'nodes: {a: {node_id: 1, tpdo: [1]}}',
     'nodes.a.tpdo: a list: allowed a mapping of keys'),
    ('tpdo-zero', 'nodes: {a: {node_id: 1, tpdo: {0: {}}}}',
     'nodes.a.tpdo.0: 0 is out of range: allowed an integer 1..512 (or its text, as "0x1A")'),
    ('tpdo-513', 'nodes: {a: {node_id: 1, rpdo: {513: {}}}}',
     'nodes.a.rpdo.513: 513 is out of range: allowed an integer 1..512 (or its text, as '
     '"0x1A")'),
    ('tpdo-name', 'nodes: {a: {node_id: 1, tpdo: {first: {}}}}',
     "nodes.a.tpdo.first: 'first' is not a number: allowed an integer 1..512 (or its text, as "
     '"0x1A")'),
    ('tpdo-twice', 'nodes: {a: {node_id: 1, tpdo: {1: {}, "1": {}}}}',
     'nodes.a.tpdo.1: PDO 1 is given twice'),
    ('tpdo-entry-list', 'nodes: {a: {node_id: 1, tpdo: {1: [1]}}}',
     'nodes.a.tpdo.1: a list: allowed a mapping of keys'),
    ('pdo-enabled-text', 'nodes: {a: {node_id: 1, tpdo: {1: {enabled: "false"}}}}',
     "nodes.a.tpdo.1.enabled: 'false' is text: allowed true or false"),
    ('pdo-cob-id-text', 'nodes: {a: {node_id: 1, tpdo: {1: {cob_id: automatic}}}}',
     "nodes.a.tpdo.1.cob_id: 'automatic' is not a number: allowed an integer 0..2047 (an "
     '11-bit CAN-ID) (or its text, as "0x1A")'),
    ('pdo-cob-id-29-bit', 'nodes: {a: {node_id: 1, tpdo: {1: {cob_id: 0x20000181}}}}',
     'nodes.a.tpdo.1.cob_id: 536871297 is out of range: allowed an integer 0..2047 (an '
     '11-bit CAN-ID) (or its text, as "0x1A")'),
    ('pdo-cob-id-nmt', 'nodes: {a: {node_id: 1, tpdo: {1: {cob_id: 0}}}}',
     'nodes.a.tpdo.1.cob_id: 0x000 is a CAN-ID CiA 301 restricts (NMT): give another'),
    ('pdo-cob-id-heartbeat', 'nodes: {a: {node_id: 1, rpdo: {2: {cob_id: "0x70A"}}}}',
     'nodes.a.rpdo.2.cob_id: 0x70A is a CAN-ID CiA 301 restricts (heartbeats and boot-ups): '
     'give another'),
    ('pdo-transmission-range', 'nodes: {a: {node_id: 1, tpdo: {1: {transmission: 256}}}}',
     'nodes.a.tpdo.1.transmission: 256 is out of range: allowed an integer 0..255'),
    ('pdo-transmission-twice',
     'nodes: {a: {node_id: 1, tpdo: {1: {transmission: 1, transmission_type: 1}}}}',
     'nodes.a.tpdo.1.transmission_type: transmission is given too: give one'),
    ('pdo-event-timer', 'nodes: {a: {node_id: 1, tpdo: {1: {event_timer: -1}}}}',
     'nodes.a.tpdo.1.event_timer: -1 is out of range: allowed an integer 0..65535 ms'),
    ('pdo-inhibit-time', 'nodes: {a: {node_id: 1, tpdo: {1: {inhibit_time: 65536}}}}',
     'nodes.a.tpdo.1.inhibit_time: 65536 is out of range: allowed an integer 0..65535 x 100 µs'),
    ('pdo-mapping-mapping', 'nodes: {a: {node_id: 1, tpdo: {1: {mapping: {index: 1}}}}}',
     'nodes.a.tpdo.1.mapping: a mapping: allowed a list (- entries)'),
    ('pdo-mapping-no-index', 'nodes: {a: {node_id: 1, tpdo: {1: {mapping: [{sub_index: 1}]}}}}',
     'nodes.a.tpdo.1.mapping[1]: no index: allowed an object index 0x0001..0xFFFF'),
    ('pdo-mapping-too-long',
     'nodes: {a: {node_id: 1, tpdo: {1: {mapping: [' + ', '.join(['{index: 1}'] * 65) + ']}}}}',
     'nodes.a.tpdo.1.mapping: 65 entries: CiA 301 allows 64'),
]


@pytest.mark.parametrize('text, message', [case[1:] for case in ERRORS],
                         ids=[case[0] for case in ERRORS])
def test_refused_with_one_message(text, message):
    assert refused(text) == f'{SHOWN}: {message}'


def test_load_names_a_file_it_cannot_read(tmp_path):
    missing = str(tmp_path / 'missing.yml')
    with pytest.raises(DescriptionError) as error:
        load(missing)
    assert str(error.value) == f'{missing!r} cannot be read: No such file or directory'
    binary = tmp_path / 'binary.yml'
    binary.write_bytes(b'\xff\xfe\x00')
    with pytest.raises(DescriptionError) as error:
        load(str(binary))
    assert str(error.value) == f'{str(binary)!r} is not UTF-8 text'


def test_software_file_and_version_are_read_and_the_file_needs_its_version():
    bus = read("""
        nodes:
          io: {node_id: 5, software_file: firmware/io.bin, software_version: "0x00010203"}
        """)
    (device,) = bus.devices
    assert device.software_version == 0x00010203
    assert device.software_file == os.path.join(os.path.dirname(PATH), 'firmware', 'io.bin')
    assert bus.unsupported == ()
    assert 'no software_version beside it' in refused("""
        nodes:
          io: {node_id: 5, software_file: io.bin}
        """)
    # 0 is no program's id: every boot would download software_file again, unchecked.
    assert 'allowed an integer 1..0xFFFFFFFF' in refused("""
        nodes:
          io: {node_id: 5, software_file: io.bin, software_version: 0}
        """)
