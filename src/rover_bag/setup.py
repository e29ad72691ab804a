"""colcon's ament_python set-up of rover_bag (its package.xml says what it is)."""
from setuptools import find_packages, setup

package_name = 'rover_bag'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', ['config/fastdds_large_shm.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Coop Field Robots maintainers',
    maintainer_email='maintainers@coop-field-robots.org',
    description='Record and replay rosbag2 (MCAP) bags of the cooperative field robot graph.',
    license='Apache-2.0',
    entry_points={'console_scripts': [
        'record = rover_bag.recorder:main',
        'play = rover_bag.player:main',
    ]},
)
