"""The installed launch file, run against stand-ins for ``launch`` and ``launch_ros``.

launch and launch_ros are not on PyPI, so ``ros2 launch`` cannot run here. The stand-ins
take exactly the keyword arguments of the real classes (Jazzy's signatures, keyword-only
where those are), so a misspelt or missing argument fails here as it would there, and record
them, so the test sees which nodes the file would start, where, and with which parameters.
"""

import importlib.util
import os
import sys
import types

from ament_index_python.packages import get_package_share_directory
from lifecycle_msgs.msg import Transition
import pytest

SHARE = get_package_share_directory('cbcan_ros')
LAUNCH_FILE = os.path.join(SHARE, 'launch', 'cbcan.launch.py')


class Recorded:
    """A launch entity that remembers how it was made."""

    def __init__(self, **kwargs):
        self.kwargs = kwargs


class LaunchDescription(Recorded):
    """launch.LaunchDescription."""

    def __init__(self, initial_entities=None, **kwargs):
        super().__init__(entities=list(initial_entities or []), **kwargs)


class DeclareLaunchArgument(Recorded):
    """launch.actions.DeclareLaunchArgument."""

    def __init__(self, name, *, default_value=None, description=None, choices=None, **kwargs):
        super().__init__(name=name, default_value=default_value, description=description,
                         choices=choices, **kwargs)


class OpaqueFunction(Recorded):
    """launch.actions.OpaqueFunction."""

    def __init__(self, *, function, args=None, kwargs=None, **left_over_kwargs):
        super().__init__(function=function, args=args, kwargs=kwargs, **left_over_kwargs)


class EmitEvent(Recorded):
    """launch.actions.EmitEvent."""

    def __init__(self, *, event, **kwargs):
        super().__init__(event=event, **kwargs)


class RegisterEventHandler(Recorded):
    """launch.actions.RegisterEventHandler."""

    def __init__(self, event_handler, **kwargs):
        super().__init__(event_handler=event_handler, **kwargs)


class LaunchConfiguration:
    """launch.substitutions.LaunchConfiguration: its value in a context."""

    def __init__(self, variable_name, *, default=None):
        self.variable_name = variable_name

    def perform(self, context):
        """Return the argument's value in ``context``."""
        return context.launch_configurations[self.variable_name]


class Node(Recorded):
    """launch_ros.actions.Node."""

    def __init__(self, *, executable, package=None, name=None, namespace=None, exec_name=None,
                 parameters=None, remappings=None, ros_arguments=None, arguments=None,
                 **kwargs):
        super().__init__(executable=executable, package=package, name=name,
                         namespace=namespace, parameters=parameters, **kwargs)


class LifecycleNode(Node):
    """launch_ros.actions.LifecycleNode: name and namespace are required."""

    def __init__(self, *, name, namespace, **kwargs):
        super().__init__(name=name, namespace=namespace, **kwargs)


class OnStateTransition(Recorded):
    """launch_ros.event_handlers.OnStateTransition."""

    def __init__(self, *, entities, target_lifecycle_node=None, transition=None,
                 start_state=None, goal_state=None, matcher=None, **kwargs):
        super().__init__(entities=entities, target_lifecycle_node=target_lifecycle_node,
                         goal_state=goal_state, **kwargs)


class ChangeState(Recorded):
    """launch_ros.events.lifecycle.ChangeState."""

    def __init__(self, *, lifecycle_node_matcher, transition_id):
        super().__init__(lifecycle_node_matcher=lifecycle_node_matcher,
                         transition_id=transition_id)


def matches_action(target_action):
    """Stand in for launch.events.matches_action: remember which node it matches."""
    return ('matches', target_action)


STAND_INS = {
    'launch': dict(LaunchDescription=LaunchDescription),
    'launch.actions': dict(DeclareLaunchArgument=DeclareLaunchArgument, EmitEvent=EmitEvent,
                           OpaqueFunction=OpaqueFunction,
                           RegisterEventHandler=RegisterEventHandler),
    'launch.events': dict(matches_action=matches_action),
    'launch.substitutions': dict(LaunchConfiguration=LaunchConfiguration),
    'launch_ros': {},
    'launch_ros.actions': dict(LifecycleNode=LifecycleNode, Node=Node),
    'launch_ros.event_handlers': dict(OnStateTransition=OnStateTransition),
    'launch_ros.events': {},
    'launch_ros.events.lifecycle': dict(ChangeState=ChangeState),
}


@pytest.fixture
def launch_file(monkeypatch):
    """Return the installed launch file as a module, imported against the stand-ins."""
    for name, attributes in STAND_INS.items():
        module = types.ModuleType(name)
        module.__dict__.update(attributes)
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location('cbcan_launch', LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run(launch_file, **given):
    """Return the actions the launch file starts for the launch arguments ``given``."""
    description = launch_file.generate_launch_description()
    arguments = {entity.kwargs['name']: entity for entity in description.kwargs['entities']
                 if isinstance(entity, DeclareLaunchArgument)}
    for name, value in given.items():
        choices = arguments[name].kwargs['choices']
        assert choices is None or value in choices, f'launch would refuse {name}:={value}'
    values = {name: argument.kwargs['default_value'] for name, argument in arguments.items()}
    values.update(given)
    function, = [entity.kwargs['function'] for entity in description.kwargs['entities']
                 if isinstance(entity, OpaqueFunction)]
    return function(types.SimpleNamespace(launch_configurations=values))


def test_by_default_one_gateway_on_can0_with_the_simulation_parameters(launch_file):
    node, = run(launch_file)
    assert type(node) is Node
    assert node.kwargs['package'] == 'cbcan_ros' and node.kwargs['executable'] == 'cbcan_node'
    assert node.kwargs['namespace'] == '/can0' and node.kwargs['name'] == 'cbcan'
    params, = node.kwargs['parameters']
    assert params == os.path.join(SHARE, 'config', 'simulation.yaml') and os.path.isfile(params)


def test_one_gateway_per_bus_in_its_own_namespace_with_the_given_file(launch_file):
    nodes = run(launch_file, buses='can0, can1', params='/robot/two_buses.yaml')
    assert [(n.kwargs['namespace'], n.kwargs['name'], n.kwargs['executable']) for n in nodes] \
        == [('/can0', 'cbcan', 'cbcan_node'), ('/can1', 'cbcan', 'cbcan_node')]
    assert all(n.kwargs['parameters'] == ['/robot/two_buses.yaml'] for n in nodes)


def test_managed_starts_lifecycle_nodes_and_configures_then_activates_them(launch_file):
    actions = run(launch_file, buses='can0,can1', managed='true')
    nodes = [a for a in actions if isinstance(a, LifecycleNode)]
    assert [(n.kwargs['namespace'], n.kwargs['executable']) for n in nodes] == \
        [('/can0', 'cbcan_lifecycle_node'), ('/can1', 'cbcan_lifecycle_node')]
    for node in nodes:
        configure, = [a.kwargs['event'] for a in actions if isinstance(a, EmitEvent)
                      and a.kwargs['event'].kwargs['lifecycle_node_matcher'][1] is node]
        assert configure.kwargs['transition_id'] == Transition.TRANSITION_CONFIGURE
        handler, = [a.kwargs['event_handler'] for a in actions
                    if isinstance(a, RegisterEventHandler)
                    and a.kwargs['event_handler'].kwargs['target_lifecycle_node'] is node]
        assert handler.kwargs['goal_state'] == 'inactive'
        activate, = handler.kwargs['entities']
        assert activate.kwargs['event'].kwargs['transition_id'] == \
            Transition.TRANSITION_ACTIVATE
        assert activate.kwargs['event'].kwargs['lifecycle_node_matcher'][1] is node


def test_managed_without_autostart_leaves_the_nodes_to_a_lifecycle_manager(launch_file):
    actions = run(launch_file, managed='true', autostart='false')
    assert [type(a) for a in actions] == [LifecycleNode]


@pytest.mark.parametrize('buses', ['', ' , ', 'can0,,can0', 'can 0', '0can', 'can0/x'])
def test_a_bad_bus_list_is_refused_naming_the_argument(launch_file, buses):
    with pytest.raises(ValueError, match='launch argument buses') as refused:
        run(launch_file, buses=buses)
    assert 'allowed: names such as can0' in str(refused.value)
