"""colcon's ament_python set-up of rover_hw (its package.xml says what it is)."""
from setuptools import find_packages, setup

package_name = 'rover_hw'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Coop Field Robots maintainers',
    maintainer_email='maintainers@coop-field-robots.org',
    description='The bridge to real rovers (serial protocol, lifecycle node) and a device '
                'emulator on a pseudo-terminal backed by rover_sim.',
    license='Apache-2.0',
    entry_points={'console_scripts': [
        'bridge = rover_hw.bridge_node:main',
        'emulator = rover_hw.emulator:main',
    ]},
)
