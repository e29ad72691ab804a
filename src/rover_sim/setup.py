"""colcon's ament_python set-up of rover_sim (its package.xml says what it is)."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'rover_sim'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Coop Field Robots maintainers',
    maintainer_email='maintainers@coop-field-robots.org',
    description='PyBullet two-rover world and its rclpy node.',
    license='Apache-2.0',
    entry_points={'console_scripts': [
        'sim = rover_sim.sim_node:main',
    ]},
)
