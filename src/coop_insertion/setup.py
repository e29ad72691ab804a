"""colcon's ament_python set-up of coop_insertion (its package.xml says what it is)."""
from setuptools import find_packages, setup

package_name = 'coop_insertion'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', ['config/insertion_world.yaml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Coop Field Robots maintainers',
    maintainer_email='maintainers@coop-field-robots.org',
    description='Cooperative insertion (thesis ch. 5): vision-guided master/slave, '
                'force-feedback finish.',
    license='Apache-2.0',
    entry_points={'console_scripts': [
        'master = coop_insertion.master_node:main',
        'slave = coop_insertion.slave_node:main',
        'driver = coop_insertion.driver_node:main',
        'force_trials = coop_insertion.force_trials:main',
        'arm_feedforward = coop_insertion.feedforward_node:main',
        'tipover_guard = coop_insertion.tipover_node:main',
        'segment_master = coop_insertion.segment_node:main_master',
        'segment_slave = coop_insertion.segment_node:main_slave',
        'segment_trials = coop_insertion.segment_trials:main',
    ]},
)
